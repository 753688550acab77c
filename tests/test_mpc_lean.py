"""Tests of the lean per-sample MPC path (kautztwin.mpc.lean): the move of MPCProblem.solve.

The lean path solves the QP in the deviation from the unconstrained optimum, skips DAQP when
that optimum meets every row, and takes no validation beyond what is free; every test here
holds it against :meth:`MPCProblem.solve` (tight tolerance) or an independent QP solution.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.optimize
import scipy.signal

from kautztwin.data import reference_system
from kautztwin.exceptions import DataError, DimensionError
from kautztwin.mpc import MPCProblem, plant_model, simulate_closed_loop

REF_LIMITS = dict(u_min=-2.5, u_max=2.5, du_min=-0.3, du_max=0.3, y_min=-0.6, y_max=1.02)
REF_STEPS = np.repeat([1.0, -0.5, 0.8, 0.0], 50)
HYD_LIMITS = dict(u_min=-14.0, u_max=20.0, du_min=-1.5, du_max=1.5, y_min=-0.65, y_max=1.01)
HYD_STEPS = np.repeat([1.0, 0.3, -0.6, 0.0], 40)
# moves are compared to 1e-9: DAQP solves both forms to the same active set, and the two
# differ by the rounding of the shifted bounds, ~1e-13 here
ATOL = 1e-9


@pytest.fixture(scope="module")
def ref_plant():
    return plant_model(reference_system(), dt=0.1)


@pytest.fixture(scope="module")
def hyd_plant():
    return plant_model(scipy.signal.lti([1.0], np.poly([-1.0, -2.0, -8.0]).real), dt=0.05)


def _replay(plant, run, *, floats: bool):
    """(x, setpoint, u_prev) of every sample of a closed loop run with the 'model' state."""
    dx = np.zeros(plant.n_states)
    up = np.zeros(plant.n_inputs)
    y = run.y.reshape(run.y.shape[0], -1)
    du = run.du.reshape(du_n := run.du.shape[0], -1)
    sp = run.setpoint.reshape(du_n, -1)
    out = []
    for k in range(du_n):
        if floats:  # what a SISO control loop passes: Python floats
            out.append((np.r_[dx, y[k]], float(sp[k, 0]), float(up[0])))
        else:
            out.append((np.r_[dx, y[k]], sp[k].copy(), up.copy()))
        dx = plant.A @ dx + plant.B @ du[k]
        up = up + du[k]
    return out


def _compare_along_loop(plant, make, steps, *, floats=True):
    """Lean moves against the closed loop of solve(); returns the share of screened samples."""
    run = simulate_closed_loop(plant, make(), steps)
    assert run.n_failed == 0
    lean = make()
    screened = 0
    for k, (x, r, up) in enumerate(_replay(plant, run, floats=floats)):
        mv = lean.move(x, r, u_prev=up)
        assert mv.success and mv.status in (0, 1)
        np.testing.assert_allclose(mv.du, np.atleast_1d(run.du[k]), rtol=0, atol=ATOL)
        np.testing.assert_allclose(mv.u, np.atleast_1d(run.u[k]), rtol=0, atol=ATOL)
        screened += mv.solver_time == 0.0
    return screened / len(steps)


class TestEqualsSolve:
    @pytest.mark.parametrize(
        "kwargs",
        [
            dict(basis=(0.8, 8)),
            dict(full_horizon=True),
            dict(basis=(0.8, 8), constraint_steps=[*range(10), *range(10, 50, 5)]),
            dict(full_horizon=True, constraint_steps=[*range(10), *range(10, 50, 5)]),
            dict(basis=(0.8, 8), warm_start=False),
        ],
    )
    def test_hydraulic_closed_loop(self, hyd_plant, kwargs):
        kw = dict(kwargs)
        basis = kw.pop("basis", None)

        def make():
            return MPCProblem(hyd_plant, basis, 50, r=0.01, **HYD_LIMITS, **kw)

        share = _compare_along_loop(hyd_plant, make, HYD_STEPS)
        assert 0.1 < share < 0.9  # both branches (screen and DAQP) were taken

    @pytest.mark.parametrize("kwargs", [dict(basis=(0.8, 8)), dict(full_horizon=True)])
    def test_longest_benchmark_horizon(self, hyd_plant, kwargs):
        # N_p = 200 (bench_mpc's longest horizon): 600 rows, 200 variables for the full MPC
        kw = dict(kwargs)
        basis = kw.pop("basis", None)

        def make():
            return MPCProblem(hyd_plant, basis, 200, r=0.01, **HYD_LIMITS, **kw)

        share = _compare_along_loop(hyd_plant, make, HYD_STEPS)
        assert 0.1 < share < 0.9

    @pytest.mark.parametrize("floats", [True, False])
    def test_reference_closed_loop(self, ref_plant, floats):
        def make():
            return MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)

        share = _compare_along_loop(ref_plant, make, REF_STEPS, floats=floats)
        assert 0.1 < share < 0.9

    def test_mimo(self):
        A = np.diag([0.9, 0.8])
        B = np.array([[0.1, 0.02], [0.03, 0.2]])
        plant = plant_model((A, B, np.eye(2)))
        kw = dict(r=[0.1, 0.2], u_max=[2.0, 1.5], du_max=0.5, du_min=-0.5, y_max=[0.6, 0.6])

        def make():
            return MPCProblem(plant, [(0.5, 4), (0.3, 3)], 30, **kw)

        run = simulate_closed_loop(plant, make(), np.tile([0.5, -0.3], (60, 1)))
        lean = make()
        for k, (x, r, up) in enumerate(_replay(plant, run, floats=False)):
            mv = lean.move(x, r, u_prev=up)
            assert mv.du.shape == mv.u.shape == (2,)
            np.testing.assert_allclose(mv.du, run.du[k], rtol=0, atol=ATOL)
            np.testing.assert_allclose(mv.u, run.u[k], rtol=0, atol=ATOL)

    def test_rows_the_inputs_cannot_move_along_a_closed_loop(self):
        # a two-sample delay: the y(k+1) rows are zero rows, screened in the same reduction
        # as the DAQP rows; the output limit binds, so DAQP runs with the zero rows met
        delay = ([[0.0, 0.0], [1.0, 0.0]], [1.0, 0.0], [0.0, 1.0])
        plant = plant_model(delay)
        kw = dict(r=0.1, y_max=1.0, y_min=-0.4, u_min=-5.0, u_max=5.0, du_max=0.8)

        def make():
            return MPCProblem(plant, (0.5, 4), 20, **kw)

        assert make()._qp._drows.zero_idx.size == 1
        share = _compare_along_loop(plant, make, np.repeat([1.2, -0.6, 0.5], 25))
        assert 0.1 < share < 0.9

    def test_lower_bound_binds(self, ref_plant):
        # DAQP's lower bounds are the screen's slacks negated back: a step down where only
        # lower limits (du_min, then y_min) can bind gives solve()'s move and du_min itself
        a = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        b = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        x = np.r_[np.zeros(4), 0.0]
        res, mv = a.solve(x, -1.0, u_prev=0.0), b.move(x, -1.0, u_prev=0.0)
        assert mv.iterations > 0 and res.success and mv.success
        assert mv.du[0] == pytest.approx(-0.3, abs=1e-9)
        assert mv.du[0] == pytest.approx(res.du[0], abs=ATOL)

    def test_screened_sample_is_the_unconstrained_law(self, ref_plant):
        problem = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        x = np.r_[np.zeros(4), 0.5]
        mv = problem.move(x, 0.52, u_prev=1.0)  # a small step: no row is near its limit
        assert mv.solver_time == 0.0 and mv.iterations == 0 and mv.status == 1 and mv.success
        e = x.copy()
        e[-1] -= 0.52
        expected = -(problem.design.K_mpc @ e)
        np.testing.assert_allclose(mv.du, expected, rtol=1e-12, atol=1e-15)
        res = problem.solve(x, 0.52, u_prev=1.0)
        assert res.success and res.du[0] == pytest.approx(mv.du[0], abs=1e-13)

    def test_constrained_sample_against_an_independent_qp(self, ref_plant):
        # the QP in eta solved by SLSQP on the public one-sided form M eta <= gamma
        problem = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        x, r, up = np.r_[np.zeros(4), 0.0], 1.0, 0.0  # a unit step: the rate limit binds
        mv = problem.move(x, r, u_prev=up)
        assert mv.iterations > 0 and mv.du[0] == pytest.approx(0.3, abs=1e-9)
        M, gamma = problem.constraints(x, up)
        E = problem.E
        e = x.copy()
        e[-1] -= r
        F = 2.0 * problem.design.Psi @ e
        sol = scipy.optimize.minimize(
            lambda z: 0.5 * z @ E @ z + F @ z,
            np.zeros(problem.n_variables),
            jac=lambda z: E @ z + F,
            constraints=[{"type": "ineq", "fun": lambda z: gamma - M @ z, "jac": lambda z: -M}],
            method="SLSQP",
            options={"ftol": 1e-14, "maxiter": 500},
        )
        assert sol.success
        du_oracle = problem.design.L0.T @ sol.x
        np.testing.assert_allclose(mv.du, du_oracle, rtol=0, atol=1e-7)


class TestFallbacks:
    """Samples the lean path hands to solve(): the compromise is solve()'s."""

    @pytest.fixture
    def at_one(self, ref_plant):
        return np.linalg.solve(np.eye(4) - ref_plant.A, ref_plant.B[:, 0] * 2.0)  # y=1, u=2

    def test_output_rows_softened(self, ref_plant, at_one):
        kw = dict(r=0.05, u_min=-2.5, u_max=2.5, du_min=-0.3, du_max=0.3, y_max=0.5)
        a, b = MPCProblem(ref_plant, (0.6, 6), 50, **kw), MPCProblem(ref_plant, (0.6, 6), 50, **kw)
        x = a.augmented_state(at_one, at_one)
        res, mv = a.solve(x, 0.0, u_prev=2.0), b.move(x, 0.0, u_prev=2.0)
        assert not res.success and not mv.success and res.status == mv.status == 2
        assert mv.du[0] == pytest.approx(res.du[0], abs=1e-12)
        assert mv.u[0] == pytest.approx(res.u_next, abs=1e-12)

    def test_clipped_when_the_input_limits_exclude_the_input(self, ref_plant):
        a = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        b = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)
        res, mv = a.solve(np.zeros(5), 0.0, u_prev=3.5), b.move(np.zeros(5), 0.0, u_prev=3.5)
        assert not mv.success and mv.status == res.status == -100
        assert mv.u[0] == pytest.approx(3.2, abs=1e-12) and mv.du[0] == res.du[0]

    def test_limits_the_inputs_cannot_move_near_their_tolerance(self):
        # y(k+1) = y(k) + dx1 of a delay plant: the inputs cannot move it.  Around the
        # limit plus its tolerance (1e-6) the lean path defers to solve(): same decision.
        delay = ([[0.0, 0.0], [1.0, 0.0]], [1.0, 0.0], [0.0, 1.0])
        kw = dict(r=0.1, y_max=1.0, u_min=-5.0, u_max=5.0)
        for over in (-1e-3, 0.0, 1e-6 * (1 - 1e-12), 1e-6, 1e-6 * (1 + 1e-9), 1e-3):
            x = [0.5 + over, 0.0, 0.5]  # y(k+1) = 1.0 + over
            res = MPCProblem(delay, (0.5, 4), 20, **kw).solve(x, 0.8, u_prev=0.5)
            mv = MPCProblem(delay, (0.5, 4), 20, **kw).move(x, 0.8, u_prev=0.5)
            assert mv.success is res.success and mv.status == res.status, over
            assert mv.du[0] == pytest.approx(res.du[0], abs=1e-12)
        assert not res.success and res.status == -101  # the last one is over

    def test_hildreth_goes_through_solve(self, ref_plant):
        kw = dict(r=0.05, solver="hildreth", constraint_steps=5, **REF_LIMITS)
        a, b = MPCProblem(ref_plant, (0.6, 6), 50, **kw), MPCProblem(ref_plant, (0.6, 6), 50, **kw)
        x = np.r_[np.zeros(4), 0.2]
        res, mv = a.solve(x, 1.0, u_prev=0.5), b.move(x, 1.0, u_prev=0.5)
        assert mv.du[0] == res.du[0] and mv.iterations == res.iterations > 0

    @pytest.mark.parametrize("solver", ["daqp", "hildreth"])
    def test_unconstrained_problem(self, solver):
        plant = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
        problem = MPCProblem(plant, (0.5, 4), 20, r=0.1, solver=solver)
        x = np.array([0.1, -0.2, 0.3])
        mv, res = problem.move(x, 1.0, u_prev=0.2), problem.solve(x, 1.0, u_prev=0.2)
        assert mv.status == res.status == 0 and mv.success
        np.testing.assert_allclose(mv.du, res.du[:1], rtol=1e-12, atol=1e-15)


@pytest.fixture(scope="module")
def pair(ref_plant):
    def make():
        return MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **REF_LIMITS)

    return make


class TestArguments:
    """No validation on the lean path: what it cannot take, solve() takes or names."""

    @pytest.mark.parametrize(
        "x, r, up",
        [
            ([0.0, 0.0, 0.0, 0.0, 0.2], 1.0, 0.5),  # list state
            ((0.0, 0.0, 0.0, 0.0, 0.2), np.float64(1.0), np.float64(0.5)),  # numpy scalars
            (np.r_[0.0, 0.0, 0.0, 0.0, 0.2], np.array([1.0]), np.array([0.5])),  # 1-element
            (np.r_[0.0, 0.0, 0.0, 0.0, 0.2][:, None], 1.0, 0.5),  # a column: through solve()
            (np.r_[0.0, 0.0, 0.0, 0.0, 0.2], 1, 0),  # ints
        ],
    )
    def test_accepted_forms_give_the_solve_move(self, pair, x, r, up):
        res = pair().solve(x, r, u_prev=up)
        mv = pair().move(x, r, u_prev=up)
        assert mv.du.shape == mv.u.shape == (1,)
        assert mv.du[0] == pytest.approx(res.du[0], abs=ATOL)
        assert mv.u[0] == pytest.approx(res.u_next, abs=ATOL)

    @pytest.mark.parametrize(
        "x, r, up, error, match",
        [
            (0.0, 1.0, 0.0, DimensionError, "x has 1 entries but 5"),
            (np.zeros(6), 1.0, 0.0, DimensionError, "x has 6 entries but 5"),
            (np.zeros(5), [1.0, 2.0], 0.0, DimensionError, "setpoint"),
            (np.zeros(5), 1.0, [0.0, 1.0], DimensionError, "u_prev"),
            (np.r_[np.zeros(4), np.nan], 1.0, 0.0, DataError, "x contains NaN"),
            (np.r_[np.inf, np.zeros(4)], 1.0, 0.0, DataError, "x contains NaN or inf"),
            (np.zeros(5), np.inf, 0.0, DimensionError, "setpoint"),
            (np.zeros(5), 1.0, -np.inf, DataError, "u_prev"),
            (np.r_[np.inf, -np.inf, 0.0, 0.0, 0.0], 1.0, 0.0, DataError, "x contains"),
        ],
    )
    def test_bad_arguments_are_named(self, pair, x, r, up, error, match):
        # pyproject turns RuntimeWarning into errors: none may leak from the lean path
        with pytest.raises(error, match=match):
            pair().move(x, r, u_prev=up)

    def test_inf_input_without_input_limits(self, ref_plant):
        # u_prev enters no bound here; the non-finite input is still caught
        problem = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, y_max=1.0)
        with pytest.raises(DataError, match="u_prev"):
            problem.move(np.zeros(5), 1.0, u_prev=np.nan)

    def test_moves_do_not_share_memory(self, pair):
        problem = pair()
        first = problem.move(np.r_[np.zeros(4), 0.5], 0.52, u_prev=1.0)  # screened
        du, u = first.du.copy(), first.u.copy()
        second = problem.move(np.zeros(5), 1.0, u_prev=0.0)  # through DAQP
        third = problem.move(np.r_[np.zeros(4), 0.5], 0.0, u_prev=1.0)
        assert second.iterations > 0
        assert first.du[0] == du[0] and first.u[0] == u[0]
        assert not np.shares_memory(first.du, third.du) and not np.shares_memory(second.u, third.u)
