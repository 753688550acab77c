"""Tests of kautztwin.mpc: Laguerre/Kautz MPC (kautz-math.md section 6, reference values 9.5)."""

from __future__ import annotations

import dataclasses

import daqp  # noqa: E402 - a core dependency
import numpy as np
import pytest
import scipy.linalg
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_poles, reference_response, reference_system
from kautztwin.exceptions import DataError, DimensionError, PoleError
from kautztwin.mpc import (
    MPCProblem,
    PlantModel,
    continuous_cost_matrices,
    continuous_mpc_design,
    continuous_phi,
    discrete_mpc_design,
    hildreth,
    plant_model,
    simulate_closed_loop,
    solve_mpc,
)

EPS = np.finfo(float).eps

# kautz-math.md 9.5 plants
DT_PLANT = ([[0.8, 0.2], [0.0, 0.7]], [0.0, 1.0], [1.0, 0.0])
DOUBLE_INTEGRATOR = ([[1.0, 1.0], [0.0, 1.0]], [0.5, 1.0], [1.0, 0.0])
CT_PLANT = ([[0.0, 1.0], [-1.0, -0.4]], [0.0, 1.0], [1.0, 0.0])  # 1/(s^2 + 0.4 s + 1)

# the discretised reference system 6/((s+1)(s+3)(s^2+s+4)), dt = 0.1, static gain 0.5
REF_DT = 0.1
LIMITS = dict(u_min=-2.5, u_max=2.5, du_min=-0.3, du_max=0.3, y_min=-0.6, y_max=1.02)
STEPS = np.r_[np.full(50, 1.0), np.full(50, -0.5), np.full(50, 0.8), np.full(50, 0.0)]


@pytest.fixture(scope="module")
def ref_plant() -> PlantModel:
    return plant_model(reference_system(), dt=REF_DT)


@pytest.fixture(scope="module")
def ref_problem(ref_plant) -> MPCProblem:
    return MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **LIMITS)


def rest_state(plant: PlantModel, u: float) -> np.ndarray:
    """Augmented state [0; y] of the plant at rest under the constant input u."""
    x_m = np.linalg.solve(np.eye(plant.n_states) - plant.A, plant.B[:, 0] * u)
    return np.r_[np.zeros(plant.n_states), plant.C @ x_m]


def classical_mpc(A, B, C, n_p, n_c, r_w):
    """Classical incremental MPC matrices: Y = F x + Phi dU (Wang 2009, ch. 1)."""
    F = np.vstack([C @ np.linalg.matrix_power(A, i) for i in range(1, n_p + 1)])
    Phi = np.zeros((n_p, n_c))
    for i in range(n_p):
        for j in range(min(i + 1, n_c)):
            Phi[i, j] = (C @ np.linalg.matrix_power(A, i - j) @ B)[0, 0]
    return F, Phi, Phi.T @ Phi + r_w * np.eye(n_c)


# ============================================================================ 9.5 reference values
class TestDiscreteReference:
    def test_laguerre_a0_equals_classical_mpc(self):
        # a = 0: L_i(k) = delta(k - i + 1), so eta_i = Delta u(k + i - 1) (kautz-math.md 6.1)
        d = discrete_mpc_design(DT_PLANT, (0.0, 4), 10, r=0.5)
        F, Phi, H = classical_mpc(d.A, d.B, d.C, 10, 4, 0.5)
        rng = np.random.default_rng(0)
        for _ in range(5):
            x, r = rng.standard_normal(3), rng.standard_normal()
            dU = np.linalg.solve(H, Phi.T @ (r * np.ones(10) - F @ x))
            # Both sides solve a 4x4 SPD system whose entries are the same 10 products
            # summed in a different order (relative difference ~ eps); the solve amplifies
            # that by at most cond(Omega) ~ 120, so |eta - dU| <= cond * eps * |dU| to first
            # order: 5e-15 for |dU| ~ 0.2 (the design note's 3e-14 is the same bound at
            # larger |dU|).  Observed differences are ~ 1e-16.
            tol = np.linalg.cond(d.Omega) * EPS * np.abs(dU).max()
            assert tol < 1e-12
            np.testing.assert_allclose(d.optimal_eta(x, r), dU, rtol=0, atol=tol)
        np.testing.assert_allclose(d.Omega, H, rtol=0, atol=20 * EPS * np.abs(H).max())

    def test_gain_and_matrices(self):
        d = discrete_mpc_design(DT_PLANT, (0.5, 4), 20, r=0.1)
        np.testing.assert_allclose(
            d.K_mpc, [[3.0828798501, 1.3081865664, 1.6215351838]], rtol=0, atol=6e-11
        )
        np.testing.assert_allclose(d.Omega[0, 0], 304.3949698549, rtol=2e-13)
        np.testing.assert_allclose(d.Psi[0, 0], 251.2565974427, rtol=2e-13)

    def test_closed_loop_poles(self):
        d = discrete_mpc_design(DT_PLANT, (0.5, 4), 20, r=0.1)
        expected = np.sort_complex(
            [0.4009497142 + 0.4155895765j, 0.4009497142 - 0.4155895765j, 0.3899140052]
        )
        np.testing.assert_allclose(d.closed_loop_poles(), expected, rtol=0, atol=6e-11)

    def test_setpoint_response(self):
        # unconstrained receding horizon, set-point 1 from rest (full state feedback)
        problem = MPCProblem(DT_PLANT, (0.5, 4), 20, r=0.1)
        res = simulate_closed_loop(DT_PLANT, problem, 1.0, 60, state_source="plant")
        np.testing.assert_allclose(
            res.y[:6], [0, 0, 0.324307, 0.710821, 0.961922, 1.053613], rtol=0, atol=5e-7
        )
        assert abs(res.y[-1] - 1.0) < 1e-12

    def test_double_integrator(self):
        d = discrete_mpc_design(DOUBLE_INTEGRATOR, (0.5, 4), 20, r=0.1)
        np.testing.assert_allclose(
            d.K_mpc, [[0.9858721184, 1.4459412497, 0.4432471323]], rtol=0, atol=6e-11
        )
        expected = np.sort_complex(
            [0.2874714028 + 0.3082150334j, 0.2874714028 - 0.3082150334j, 0.2645563194]
        )
        np.testing.assert_allclose(d.closed_loop_poles(), expected, rtol=0, atol=6e-11)


class TestContinuousReference:
    def test_gain_and_matrices(self):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05)
        np.testing.assert_allclose(
            d.K_mpc, [[5.7258681981, 3.3676289003, 4.8810602908]], rtol=0, atol=6e-11
        )
        np.testing.assert_allclose(d.Omega[0, 0], 17.5096773075, rtol=0, atol=6e-11)
        np.testing.assert_allclose(
            d.Psi[0], [5.1663124936, 13.1744174749, 12.0398240706], rtol=0, atol=6e-11
        )

    def test_closed_loop_poles(self):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05)
        expected = np.sort_complex(
            [-1.1584903488 + 1.4221970416j, -1.1584903488 - 1.4221970416j, -1.4506482026]
        )
        np.testing.assert_allclose(d.closed_loop_poles(), expected, rtol=0, atol=6e-11)

    def test_exact_finite_horizon_penalty(self):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05, penalty="finite")
        np.testing.assert_allclose(
            d.K_mpc, [[5.7259671213, 3.3676415464, 4.8811790093]], rtol=0, atol=6e-11
        )
        Ep = scipy.linalg.expm(d.A_L * 10.0)
        np.testing.assert_allclose(d.R_L, 0.05 * (np.eye(4) - Ep @ Ep.T), atol=1e-16)

    @pytest.mark.parametrize("T_p", [10.0, 40.0], ids=["pTp=10", "pTp=40"])
    def test_van_loan_matches_quadrature(self, T_p):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), T_p, r=0.05)
        args = (d.A, d.B, d.A_L, d.L0, d.Q, T_p)
        vl = continuous_cost_matrices(*args)
        gq = continuous_cost_matrices(*args, method="quadrature", n_panels=60)
        # design note: 4e-11 / 2e-10 absolute at T_p = 10; interval doubling does better
        for a, b in zip(vl, gq, strict=True):
            np.testing.assert_allclose(a, b, rtol=0, atol=1e-12 * np.abs(b).max())

    def test_van_loan_without_doubling_degrades(self):
        # the reason for the doubling: a single Van Loan exponential over p T_p = 40 is useless
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 40.0, r=0.05)
        args = (d.A, d.B, d.A_L, d.L0, d.Q, 40.0)
        single = continuous_cost_matrices(*args, n_doublings=0)[0]
        doubled = continuous_cost_matrices(*args)[0]
        assert np.abs(single - doubled).max() > 1e-3 * np.abs(doubled).max()

    @pytest.mark.parametrize("tau", [0.3, 2.0, 10.0])
    def test_phi_sylvester_matches_block_exponential(self, tau):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05)
        a = continuous_phi(d.A, d.B, d.A_L, d.L0, tau)
        b = continuous_phi(d.A, d.B, d.A_L, d.L0, tau, method="sylvester")
        np.testing.assert_allclose(a, b, rtol=0, atol=5e-14)

    def test_phi_is_the_convolution_integral(self):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05)
        tau = 1.5
        x, w = np.polynomial.legendre.leggauss(30)
        g = 0.5 * tau * (x + 1)
        integrand = [
            scipy.linalg.expm(d.A * (tau - gi)) @ d.B @ (scipy.linalg.expm(d.A_L * gi) @ d.L0).T
            for gi in g
        ]
        quad = 0.5 * tau * np.tensordot(w, np.array(integrand), axes=1)
        np.testing.assert_allclose(continuous_phi(d.A, d.B, d.A_L, d.L0, tau), quad, atol=1e-13)

    def test_mimo_design(self):
        plant = (np.array([[-1.0, 0.2], [0.0, -2.0]]), np.eye(2), np.eye(2))
        d = continuous_mpc_design(plant, [(-1.0, 3), (-2.0, 2)], 5.0, r=[0.1, 0.2])
        assert d.K_mpc.shape == (2, 4) and d.n_functions == 5
        assert d.closed_loop_poles().real.max() < 0
        assert not d.L0[:3, 1].any() and not d.L0[3:, 0].any()  # one basis per input

    def test_closed_loop_tracks_unit_setpoint(self):
        d = continuous_mpc_design(CT_PLANT, (-1.0, 4), 10.0, r=0.05)
        x_s = np.array([0.0, 0.0, 1.0])
        x30 = x_s + scipy.linalg.expm((d.A - d.B @ d.K_mpc) * 30.0) @ (np.zeros(3) - x_s)
        assert abs((d.C @ x30)[0] - 1.0) < 1e-13


# ============================================================================ constrained MPC
class TestConstrainedTracking:
    @pytest.mark.parametrize(
        "basis",
        [(0.6, 6), kt.KautzBasis([0.7, 0.5 + 0.3j, 0.5 - 0.3j, 0.6], dt=REF_DT)],
        ids=["laguerre", "kautz"],
    )
    def test_zero_violations(self, ref_plant, basis):
        problem = MPCProblem(ref_plant, basis, 50, r=0.05, **LIMITS)
        res = simulate_closed_loop(ref_plant, problem, STEPS)
        assert res.violations == 0 and res.n_failed == 0
        assert res.max_violation <= 1e-8
        # the limits are active (the test is not vacuous) and every plateau is reached
        assert np.isclose(np.abs(res.du).max(), 0.3) and res.y.max() > 1.0
        for end, r in zip([50, 100, 150, 200], [1.0, -0.5, 0.8, 0.0], strict=True):
            assert abs(res.y[end] - r) < 1e-2  # 5 s plateaus, lightly damped plant

    def test_identified_model_on_true_plant(self):
        # identify a Kautz model from the sampled impulse response, control the true system
        t, h = reference_response(kind="impulse", n_samples=900, t_end=20.0)
        model = kt.approximate(kt.KautzBasis(reference_poles()), t, h).model
        problem = MPCProblem(model, (0.6, 6), 50, dt=REF_DT, r=0.05, **LIMITS)
        res = simulate_closed_loop(reference_system(), problem, STEPS)
        assert res.violations == 0 and res.n_failed == 0
        assert abs(res.y[-1]) < 1e-2 and abs(res.y[150] - 0.8) < 1e-2

    @pytest.mark.parametrize(("source", "tol"), [("model", 1e-3), ("plant", 1e-6)])
    def test_input_disturbance_rejected_offset_free(self, ref_plant, ref_problem, source, tol):
        # a load step at k = 60; 'model' sees it only through y (slower), 'plant' also via x
        d = np.r_[np.zeros(60), np.full(140, 0.3)]
        res = simulate_closed_loop(ref_plant, ref_problem, 0.5, 200, d, state_source=source)
        assert abs(res.y[-1] - 0.5) < tol and res.violations == 0

    def test_limits_change_the_move(self, ref_problem, ref_plant):
        free = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05)
        x = np.zeros(5)
        assert free.solve(x, 1.0).du[0] > 0.3
        res = ref_problem.solve(x, 1.0)
        assert res.success and res.iterations > 0
        assert res.du[0] == pytest.approx(0.3, abs=1e-9)

    def test_full_horizon_same_cost_and_constraints(self, ref_plant):
        full = MPCProblem(ref_plant, None, 50, r=0.05, full_horizon=True, **LIMITS)
        lag0 = MPCProblem(ref_plant, (0.0, 50), 50, r=0.05, **LIMITS)
        assert full.n_variables == 50 and full.full_horizon
        np.testing.assert_allclose(full.E, lag0.E, atol=1e-12)
        x = rest_state(ref_plant, 0.5)
        a, b = full.solve(x, 1.0, u_prev=0.5), lag0.solve(x, 1.0, u_prev=0.5)
        assert a.success and b.success
        np.testing.assert_allclose(a.eta, b.eta, atol=1e-7)
        np.testing.assert_allclose(a.du, a.eta, atol=1e-15)  # one variable per step

    def test_full_horizon_simple_bounds_agree_with_hildreth(self, ref_plant):
        kw = dict(r=0.05, full_horizon=True, constraint_steps=10, **LIMITS)
        d = MPCProblem(ref_plant, None, 30, **kw)
        h = MPCProblem(ref_plant, None, 30, solver="hildreth", tol=1e-13, max_iter=200000, **kw)
        x = np.zeros(5)
        a, b = d.solve(x, 1.0), h.solve(x, 1.0)
        assert a.success and b.success
        np.testing.assert_allclose(a.eta, b.eta, atol=1e-7)

    @pytest.mark.parametrize("steps", [None, [2, 5]], ids=["all-steps", "steps-2-5"])
    def test_full_horizon_rate_limits_only(self, steps):
        # only simple bounds (no general rows) for DAQP; with a subset, the others are free
        p = MPCProblem(
            DT_PLANT, None, 20, full_horizon=True, du_min=-0.1, du_max=0.1, constraint_steps=steps
        )
        h = MPCProblem(
            DT_PLANT,
            None,
            20,
            full_horizon=True,
            du_min=-0.1,
            du_max=0.1,
            constraint_steps=steps,
            solver="hildreth",
            tol=1e-13,
            max_iter=100000,
        )
        a, b = p.solve(np.zeros(3), 1.0), h.solve(np.zeros(3), 1.0)
        assert a.success and b.success
        np.testing.assert_allclose(a.eta, b.eta, atol=1e-8)
        limited = slice(None) if steps is None else steps
        assert np.all(np.abs(a.du[limited]) <= 0.1 + 1e-9)

    def test_constraint_steps_subset(self, ref_plant):
        p = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, constraint_steps=[0, 1, 2], **LIMITS)
        q = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, constraint_steps=3, **LIMITS)
        assert p.n_constraints == q.n_constraints == 3 * 3
        np.testing.assert_allclose(p.solve(np.zeros(5), 1.0).eta, q.solve(np.zeros(5), 1.0).eta)

    def test_one_sided_constraint_form(self, ref_problem):
        up = 0.4
        x = rest_state(ref_problem.plant, up)
        M, gamma = ref_problem.constraints(x, up)
        assert M.shape == (2 * ref_problem.n_constraints, ref_problem.n_variables)
        res = ref_problem.solve(x, 1.0, u_prev=up)
        assert np.all(M @ res.eta <= gamma + 1e-8)
        # the rows hold the documented quantities: Delta u, u and y along the horizon
        lim = ref_problem.limits
        assert np.all(res.du <= lim["du_max"][0] + 1e-8) and np.all(res.u <= lim["u_max"][0] + 1e-8)
        assert np.all(res.y_pred <= lim["y_max"][0] + 1e-8)

    def test_mimo_tracking(self):
        # two coupled first-order loops, one Laguerre basis per input
        A = np.diag([0.9, 0.8])
        B = np.array([[0.1, 0.02], [0.03, 0.2]])
        plant = (A, B, np.eye(2))
        problem = MPCProblem(
            plant, [(0.5, 4), (0.3, 3)], 30, r=[0.1, 0.2], u_max=[2.0, 2.0], du_max=0.5, du_min=-0.5
        )
        assert problem.n_variables == 7 and problem.design.K_mpc.shape == (2, 4)
        res = simulate_closed_loop(plant, problem, np.tile([0.5, -0.3], (80, 1)))
        assert res.y.shape == (81, 2) and res.violations == 0
        np.testing.assert_allclose(res.y[-1], [0.5, -0.3], atol=1e-6)


class TestInfeasible:
    @pytest.fixture
    def at_one(self, ref_plant):
        x_m = np.linalg.solve(np.eye(4) - ref_plant.A, ref_plant.B[:, 0] * 2.0)  # y = 1, u = 2
        return x_m

    def test_output_limit_flagged_and_softened(self, ref_plant, at_one):
        # y = 1 now; y(k+1) <= 0.5 is unreachable within one sample
        problem = MPCProblem(
            ref_plant,
            (0.6, 6),
            50,
            r=0.05,
            u_min=-2.5,
            u_max=2.5,
            du_min=-0.3,
            du_max=0.3,
            y_max=0.5,
        )
        res = problem.solve(problem.augmented_state(at_one, at_one), 0.0, u_prev=2.0)
        assert not res.success and "infeasible" in res.message and "soft" in res.message
        assert res.status == 2 and res.max_violation > 0.4
        # the compromise keeps the (hard) input limits and moves down as fast as allowed
        np.testing.assert_allclose(res.du[:3], -0.3, atol=1e-6)

    def test_input_limits_infeasible_fall_back_to_clipping(self, ref_problem):
        # u_prev = 3.5 is above u_max = 2.5 and the rate limit allows only 0.3 per step
        res = ref_problem.solve(np.zeros(5), 0.0, u_prev=3.5)
        assert not res.success and "clipped" in res.message and res.status == -100
        assert res.u_next == pytest.approx(3.2, abs=1e-12)

    def test_hildreth_flags_non_convergence(self, ref_plant, at_one):
        problem = MPCProblem(
            ref_plant,
            (0.6, 6),
            50,
            r=0.05,
            y_max=0.5,
            du_min=-0.3,
            du_max=0.3,
            solver="hildreth",
            max_iter=300,
        )
        res = problem.solve(problem.augmented_state(at_one, at_one), 0.0, u_prev=2.0)
        assert not res.success and "Hildreth" in res.message and res.status == -4

    def test_closed_loop_counts_failures(self, ref_plant):
        problem = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, y_max=0.2, du_max=0.3, du_min=-0.3)
        res = simulate_closed_loop(ref_plant, problem, 0.0, 5, x0=np.array([0, 0, 0, 8.0]))
        assert res.n_failed > 0 and res.violations > 0


# ============================================================================ Hildreth
class TestHildreth:
    @pytest.mark.parametrize("seed", range(6))
    def test_matches_daqp(self, seed):
        rng = np.random.default_rng(seed)
        n, m = 6, 12
        R = rng.standard_normal((n, n))
        E = R @ R.T + n * np.eye(n)  # strictly convex
        F = 5.0 * rng.standard_normal(n)
        M = rng.standard_normal((m, n))
        gamma = rng.uniform(0.1, 1.0, m)  # x = 0 is strictly feasible
        res = hildreth(E, F, M, gamma, tol=1e-14, max_iter=100000)
        assert res.converged and res.iterations > 0
        x, _, flag, _ = daqp.solve(E, F, M, gamma, np.full(m, -1e30), primal_tol=1e-12)
        assert flag == 1
        np.testing.assert_allclose(res.x, x, rtol=0, atol=1e-8)
        # KKT: multipliers are non-negative and complementary
        assert np.all(res.lam >= 0)
        assert np.abs(res.lam * (M @ res.x - gamma)).max() < 1e-8

    def test_unconstrained_optimum_returned_directly(self):
        res = hildreth(2 * np.eye(2), [-2.0, 0.0], [[1.0, 0.0]], [5.0])
        assert res.iterations == 0 and res.converged
        np.testing.assert_allclose(res.x, [1.0, 0.0])

    def test_infinite_rows_ignored(self):
        res = hildreth(2 * np.eye(2), [-2.0, -2.0], [[1.0, 1.0], [1.0, 0.0]], [1.0, np.inf])
        np.testing.assert_allclose(res.x, [0.5, 0.5], atol=1e-10)
        assert res.lam[1] == 0.0

    def test_errors(self):
        with pytest.raises(DataError, match="positive definite"):
            hildreth(-np.eye(2), [0, 0], [[1, 0]], [1])
        with pytest.raises(DimensionError, match="gamma has 2 entries"):
            hildreth(np.eye(2), [0, 0], [[1, 0]], [1, 2])
        with pytest.raises(DataError, match="-inf"):
            hildreth(np.eye(2), [0, 0], [[1, 0]], [-np.inf])

    def test_problem_with_hildreth_matches_daqp(self, ref_plant, ref_problem):
        h = MPCProblem(
            ref_plant, (0.6, 6), 50, r=0.05, solver="hildreth", tol=1e-13, max_iter=100000, **LIMITS
        )
        for sp in (1.0, -0.5):
            a, b = ref_problem.solve(np.zeros(5), sp), h.solve(np.zeros(5), sp)
            assert a.success and b.success
            np.testing.assert_allclose(a.eta, b.eta, rtol=0, atol=1e-8)


# ============================================================================ prediction
class TestPrediction:
    def test_what_if_equals_dlsim(self, ref_plant, ref_problem):
        rng = np.random.default_rng(1)
        u = rng.standard_normal(80)
        x0 = rng.standard_normal(4)
        _, y_ref, _ = scipy.signal.dlsim(ref_plant.to_scipy(), u, x0=x0)
        y = ref_problem.what_if(u, x0)
        assert y.shape == (80,)
        np.testing.assert_allclose(y, y_ref[:, 0], rtol=0, atol=1e-13)

    def test_solve_prediction_equals_simulation(self, ref_plant, ref_problem):
        rng = np.random.default_rng(2)
        x_prev = rng.standard_normal(4) * 0.1
        u_prev = 0.7
        x_m = ref_plant.A @ x_prev + ref_plant.B[:, 0] * u_prev
        res = ref_problem.solve(ref_problem.augmented_state(x_m, x_prev), 1.0, u_prev=u_prev)
        # simulating the plan from x_m reproduces the predicted outputs y(k+1..k+Np)
        y = ref_problem.what_if(np.r_[res.u, 0.0], x_m)
        np.testing.assert_allclose(res.y_pred, y[1:], rtol=0, atol=1e-12)
        np.testing.assert_allclose(np.diff(np.r_[u_prev, res.u]), res.du, atol=1e-14)
        pred = ref_problem.predict(ref_problem.augmented_state(x_m, x_prev), res.eta, u_prev=u_prev)
        np.testing.assert_allclose(pred.y, res.y_pred, atol=1e-14)
        np.testing.assert_allclose(pred.u, res.u, atol=1e-14)

    def test_cost_is_the_horizon_cost(self, ref_problem):
        x = rest_state(ref_problem.plant, 0.3)
        res = ref_problem.solve(x, 1.0, u_prev=0.3)
        J = np.sum((res.y_pred - 1.0) ** 2) + 0.05 * np.sum(res.eta**2)
        assert res.cost == pytest.approx(J, rel=1e-10)

    def test_mimo_what_if_shape(self):
        plant = (np.diag([0.5, 0.4]), np.eye(2), np.eye(2))
        p = MPCProblem(plant, (0.3, 3), 10)
        y = p.what_if(np.ones((5, 2)))
        np.testing.assert_allclose(y[:, 0], [0, 1, 1.5, 1.75, 1.875])


# ============================================================================ API behaviour
class TestAPI:
    def test_unconstrained_solve_is_the_design_law(self):
        p = MPCProblem(DT_PLANT, (0.5, 4), 20, r=0.1)
        x = np.array([0.1, -0.2, 0.3])
        res = p.solve(x, 1.0, u_prev=0.2)
        assert res.success and res.iterations == 0 and p.n_constraints == 0
        np.testing.assert_allclose(res.eta, p.design.optimal_eta(x, 1.0), atol=1e-13)
        du0 = -(p.design.K_mpc @ (x - [0, 0, 1.0]))[0]
        assert res.u_next == pytest.approx(0.2 + du0, abs=1e-13)

    def test_solve_mpc_one_shot(self, ref_plant, ref_problem):
        x = np.zeros(5)
        a = solve_mpc(ref_plant, x, 1.0, basis=(0.6, 6), horizon=50, r=0.05, **LIMITS)
        np.testing.assert_allclose(a.eta, ref_problem.solve(x, 1.0).eta, atol=1e-10)

    def test_warm_start_and_timing_reported(self, ref_plant):
        p = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **LIMITS)
        first = p.solve(np.zeros(5), 1.0)
        again = p.solve(np.zeros(5), 1.0)
        assert again.iterations <= first.iterations
        assert first.solve_time > 0 and first.solver_time > 0
        cold = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, warm_start=False, **LIMITS)
        cold.solve(np.zeros(5), 1.0)
        assert cold.solve(np.zeros(5), 1.0).iterations == first.iterations
        np.testing.assert_allclose(cold.solve(np.zeros(5), 1.0).eta, again.eta, atol=1e-9)

    def test_results_are_frozen(self, ref_problem, ref_plant):
        res = ref_problem.solve(np.zeros(5), 1.0)
        with pytest.raises(dataclasses.FrozenInstanceError):
            res.success = False
        with pytest.raises(ValueError, match="read-only"):
            res.u[0] = 1.0
        cl = simulate_closed_loop(ref_plant, ref_problem, 0.5, 3)
        with pytest.raises(ValueError, match="read-only"):
            cl.y[0] = 1.0

    def test_continuous_plant_discretised_with_zoh(self):
        sysc = scipy.signal.lti([1.0], [1.0, 3.0, 2.0])
        P = plant_model(sysc, dt=0.05)
        ref = scipy.signal.cont2discrete(
            (sysc.to_ss().A, sysc.to_ss().B, sysc.to_ss().C, sysc.to_ss().D), 0.05
        )
        np.testing.assert_allclose(P.A, ref[0], rtol=1e-14)
        np.testing.assert_allclose(P.B, ref[1], rtol=1e-14)

    def test_kautz_model_plant(self):
        basis = kt.KautzBasis(reference_poles())
        model = kt.KautzModel(basis, kt.coefficients_from_system(basis, reference_system()))
        a = plant_model(model, dt=REF_DT)
        b = plant_model(reference_system(), dt=REF_DT)
        # same system in another realisation: compare Markov parameters
        ma = [(a.C @ np.linalg.matrix_power(a.A, k) @ a.B)[0, 0] for k in range(10)]
        mb = [(b.C @ np.linalg.matrix_power(b.A, k) @ b.B)[0, 0] for k in range(10)]
        np.testing.assert_allclose(ma, mb, atol=1e-12)

    def test_dlti_plant(self):
        A, B, C = (np.atleast_2d(m) for m in DT_PLANT)
        sysd = scipy.signal.dlti(A, B.T, C, np.zeros((1, 1)), dt=0.5)
        p = MPCProblem(sysd, (0.5, 4), 20, r=0.1)
        assert p.dt == 0.5
        np.testing.assert_allclose(p.design.K_mpc[0, 0], 3.0828798501, atol=1e-10)


class TestErrors:
    def test_feedthrough_rejected(self):
        with pytest.raises(DataError, match="feedthrough"):
            plant_model((np.eye(1) * 0.5, [[1.0]], [[1.0]], [[0.3]]))

    def test_continuous_plant_needs_dt(self):
        with pytest.raises(DataError, match="pass dt"):
            plant_model(reference_system())

    def test_dt_mismatch(self):
        with pytest.raises(DataError, match="differs"):
            plant_model(scipy.signal.dlti([1.0], [1.0, -0.5], dt=0.1), dt=0.2)

    def test_unsupported_plant(self):
        with pytest.raises(DataError, match="plant must be"):
            plant_model("not a plant")

    def test_basis_domain(self):
        with pytest.raises(DataError, match="continuous-time"):
            discrete_mpc_design(DT_PLANT, kt.LaguerreBasis(-1.0, 3), 10)
        with pytest.raises(DataError, match="discrete-time"):
            continuous_mpc_design(CT_PLANT, kt.LaguerreBasis(0.5, 3, dt=1.0), 5.0)
        with pytest.raises(DataError, match="delayed"):
            discrete_mpc_design(DT_PLANT, kt.LaguerreBasis(0.5, 3, dt=1.0, delayed=True), 10)
        with pytest.raises(PoleError, match="Laguerre pole"):
            continuous_mpc_design(CT_PLANT, (1.0, 4), 5.0)

    def test_bad_limits(self):
        with pytest.raises(DataError, match=r"u_min\[0\] = 2 exceeds u_max\[0\] = 1"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, u_min=2.0, u_max=1.0)
        with pytest.raises(DataError, match="du_min <= 0 <= du_max"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, du_min=0.1)
        with pytest.raises(DimensionError, match="y_max must be a scalar or have shape"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, y_max=[1.0, 2.0])

    def test_bad_options(self):
        with pytest.raises(DataError, match="solver must be"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, solver="osqp")
        with pytest.raises(DataError, match="basis is required"):
            MPCProblem(DT_PLANT, None, 20)
        with pytest.raises(DataError, match="not both"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, full_horizon=True)
        with pytest.raises(DataError, match="horizon must be"):
            MPCProblem(DT_PLANT, (0.5, 4), 0)
        with pytest.raises(DimensionError, match="Q must be"):
            MPCProblem(DT_PLANT, (0.5, 4), 20, Q=np.eye(2))
        with pytest.raises(DimensionError, match="basis lists 2 bases"):
            MPCProblem(DT_PLANT, [(0.5, 4), (0.5, 4)], 20)

    def test_bad_solve_arguments(self, ref_problem):
        with pytest.raises(DimensionError, match="x has 3 entries but 5"):
            ref_problem.solve(np.zeros(3), 1.0)
        with pytest.raises(DimensionError, match="setpoint"):
            ref_problem.solve(np.zeros(5), [1.0, 2.0])
        with pytest.raises(DataError, match="NaN"):
            ref_problem.solve(np.full(5, np.nan), 1.0)
        with pytest.raises(DimensionError, match="inputs"):
            ref_problem.what_if(np.zeros((4, 2)))

    def test_closed_loop_arguments(self, ref_plant, ref_problem):
        with pytest.raises(DataError, match="n_steps is required"):
            simulate_closed_loop(ref_plant, ref_problem, 1.0)
        with pytest.raises(DimensionError, match="disturbances"):
            simulate_closed_loop(ref_plant, ref_problem, 1.0, 5, np.zeros(3))
        with pytest.raises(DimensionError, match="state_source='plant'"):
            simulate_closed_loop(
                (np.eye(1) * 0.5, [[1.0]], [[1.0]]), ref_problem, 1.0, 5, state_source="plant"
            )


# ============================================================================ lean path
def _replay_states(plant: PlantModel, run) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(x, setpoint, u_prev) of every solve of a closed-loop run with the 'model' state."""
    dx = np.zeros(plant.n_states)
    u_prev = np.zeros(plant.n_inputs)
    y = run.y.reshape(run.y.shape[0], -1)
    du = run.du.reshape(run.du.shape[0], -1)
    u = run.u.reshape(run.u.shape[0], -1)
    sp = run.setpoint.reshape(run.setpoint.shape[0], -1)
    out = []
    for k in range(du.shape[0]):
        out.append((np.r_[dx, y[k]], sp[k], u_prev))
        dx = plant.A @ dx + plant.B @ du[k]
        u_prev = u[k]
    return out


class TestLeanMove:
    """MPCProblem.move is the first move of MPCProblem.solve, with the same warm start."""

    @pytest.mark.parametrize(
        "kwargs",
        [
            dict(basis=(0.8, 8)),
            dict(full_horizon=True),
            dict(basis=(0.6, 6), constraint_steps=[0, 1, 2, 5, 10, 20, 40]),
            dict(basis=(0.8, 8), warm_start=False),
            # Hildreth goes through solve(); a short run keeps its sweeps cheap
            dict(basis=(0.6, 6), solver="hildreth", n_steps=4),
        ],
    )
    def test_equals_solve_along_a_closed_loop(self, ref_plant, kwargs):
        kw = dict(kwargs)
        basis = kw.pop("basis", None)
        steps = STEPS[: kw.pop("n_steps", STEPS.size)]
        run = simulate_closed_loop(
            ref_plant, MPCProblem(ref_plant, basis, 50, r=0.05, **LIMITS, **kw), steps
        )
        assert int(np.max(run.iterations)) > 0  # constraints were active
        lean = MPCProblem(ref_plant, basis, 50, r=0.05, **LIMITS, **kw)
        for k, (x, r, u_prev) in enumerate(_replay_states(ref_plant, run)):
            mv = lean.move(x, float(r[0]), u_prev=float(u_prev[0]))
            assert mv.du.shape == (1,) and mv.u.shape == (1,)
            # the QP is solved to DAQP's default tolerances; 1e-9 leaves room for the rounding
            # of the one-product bounds against solve()'s two-step sums, nothing more
            assert mv.du[0] == pytest.approx(run.du[k], abs=1e-9)
            assert mv.u[0] == pytest.approx(run.u[k], abs=1e-9)

    def test_mixing_solve_and_move_keeps_the_sequence(self, ref_plant):
        run = simulate_closed_loop(ref_plant, MPCProblem(ref_plant, (0.8, 8), 50, **LIMITS), STEPS)
        mixed = MPCProblem(ref_plant, (0.8, 8), 50, **LIMITS)
        for k, (x, r, u_prev) in enumerate(_replay_states(ref_plant, run)):
            if k % 3:
                du0 = mixed.move(x, r, u_prev=u_prev).du[0]
            else:
                du0 = mixed.solve(x, r, u_prev=u_prev).du[0]
            assert du0 == pytest.approx(run.du[k], abs=1e-9)

    def test_unconstrained_is_the_design_law(self):
        problem = MPCProblem(DT_PLANT, (0.5, 4), 20, r=0.1)
        assert problem.n_constraints == 0
        rng = np.random.default_rng(3)
        for _ in range(5):
            x, r, up = rng.normal(size=3), rng.normal(), rng.normal()
            e = x.copy()
            e[-1] -= r
            mv = problem.move(x, r, u_prev=up)
            expected = -(problem.design.K_mpc @ e)
            np.testing.assert_allclose(mv.du, expected, rtol=1e-12, atol=1e-14)
            np.testing.assert_allclose(mv.u, up + expected, rtol=1e-12, atol=1e-14)
            assert mv.status == 0 and mv.iterations == 0

    def test_mimo(self):
        A = np.diag([0.9, 0.8])
        B = np.array([[0.1, 0.02], [0.03, 0.2]])
        plant = plant_model((A, B, np.eye(2)))
        kw = dict(r=[0.1, 0.2], u_max=[2.0, 2.0], du_max=0.5, du_min=-0.5, y_max=[0.6, 0.6])
        run = simulate_closed_loop(
            plant, MPCProblem(plant, [(0.5, 4), (0.3, 3)], 30, **kw), np.tile([0.5, -0.3], (60, 1))
        )
        lean = MPCProblem(plant, [(0.5, 4), (0.3, 3)], 30, **kw)
        for k, (x, r, u_prev) in enumerate(_replay_states(plant, run)):
            mv = lean.move(x, r, u_prev=u_prev)
            assert mv.du.shape == (2,)
            np.testing.assert_allclose(mv.du, run.du[k], atol=1e-9)

    def test_infeasible_falls_back_to_the_compromise(self, ref_plant):
        x_m = np.linalg.solve(np.eye(4) - ref_plant.A, ref_plant.B[:, 0] * 2.0)  # y = 1, u = 2
        kw = dict(r=0.05, u_min=-2.5, u_max=2.5, du_min=-0.3, du_max=0.3, y_max=0.5)
        full = MPCProblem(ref_plant, (0.6, 6), 50, **kw)
        lean = MPCProblem(ref_plant, (0.6, 6), 50, **kw)
        x = full.augmented_state(x_m, x_m)
        res = full.solve(x, 0.0, u_prev=2.0)
        mv = lean.move(x, 0.0, u_prev=2.0)
        assert not res.success and not mv.success and mv.status == res.status == 2
        assert mv.du[0] == pytest.approx(res.du[0], abs=1e-12)
        assert mv.u[0] == pytest.approx(res.u_next, abs=1e-12)

    def test_bad_arguments_name_the_problem(self, ref_problem):
        with pytest.raises(DimensionError, match="x has 1 entries but 5"):
            ref_problem.move(0.0, 1.0)
        with pytest.raises(DimensionError, match="x has 3 entries but 5"):
            ref_problem.move(np.zeros(3), 1.0)
        with pytest.raises(DimensionError, match="setpoint"):
            ref_problem.move(np.zeros(5), [1.0, 2.0])
        with pytest.raises(DataError, match="NaN"):
            ref_problem.move(np.full(5, np.nan), 1.0)
        with pytest.raises(DataError, match="u_prev"):
            ref_problem.move(np.zeros(5), 1.0, u_prev=np.inf)

    def test_move_is_immutable(self, ref_problem):
        mv = ref_problem.move(np.zeros(5), 1.0)
        with pytest.raises(AttributeError):
            mv.du = np.zeros(1)  # type: ignore[misc]


class TestRowScaling:
    """Output rows that the inputs move only a little, or not at all."""

    # 1600/((s+1)(s+20)(s+80)) sampled fast: y(k+1) moves with C B ~ 3e-8
    FAST = scipy.signal.lti([1600.0], np.poly([-1.0, -20.0, -80.0]).real)

    def test_small_output_rows_are_kept(self):
        # unscaled, DAQP took these rows for zero rows: the setup failed ("infeasible", the
        # limits 70..130 exclude 0) or, set up without bounds, it ignored the output limits
        plant = plant_model(self.FAST, dt=0.0005)
        kw = dict(r=0.01, y_min=70.0, y_max=130.0, u_min=0.0, u_max=200.0)
        problem = MPCProblem(plant, (0.9, 6), 50, **kw)
        inside = problem.solve(np.r_[np.zeros(plant.n_states), 100.0], 105.0, u_prev=100.0)
        assert inside.success and np.all(inside.y_pred <= 130.0 + 1e-9)
        # above y_max, and the plant cannot come down within 25 ms: flagged, softened
        above = problem.solve(np.r_[np.zeros(plant.n_states), 140.0], 100.0, u_prev=100.0)
        assert not above.success and above.status == 2 and above.max_violation > 9.0
        assert above.u_next == pytest.approx(0.0, abs=1e-6)  # down as hard as allowed
        lean = MPCProblem(plant, (0.9, 6), 50, **kw)
        mv = lean.move(np.r_[np.zeros(plant.n_states), 140.0], 100.0, u_prev=100.0)
        assert not mv.success and mv.du[0] == pytest.approx(above.du[0], abs=1e-9)

    def test_scaling_leaves_the_solution_unchanged(self, ref_plant):
        # on a well-scaled problem the result equals Hildreth's on the unscaled rows
        d = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, **LIMITS)
        h = MPCProblem(ref_plant, (0.6, 6), 50, r=0.05, solver="hildreth", **LIMITS)
        x = np.r_[np.zeros(4), 0.2]
        a, b = d.solve(x, 1.0, u_prev=0.5), h.solve(x, 1.0, u_prev=0.5)
        assert a.success and b.success
        np.testing.assert_allclose(a.eta, b.eta, atol=1e-6)

    def test_limits_the_inputs_cannot_move_are_reported(self):
        # a one-sample delay before the output: y(k+1) does not depend on u(k) at all
        delay = ([[0.0, 0.0], [1.0, 0.0]], [1.0, 0.0], [0.0, 1.0])
        kw = dict(r=0.1, y_max=1.0, u_min=-5.0, u_max=5.0)
        problem = MPCProblem(delay, (0.5, 4), 20, **kw)
        ok = problem.solve([0.0, 0.0, 0.5], 0.8, u_prev=0.0)
        assert ok.success and ok.status == 1
        # y(k) = 0.5 and x1 grew by 1.5: y(k+1) = 2 > y_max, whatever the input does
        bad = problem.solve([1.5, 0.0, 0.5], 0.8, u_prev=1.5)
        assert not bad.success and bad.status == -101 and "cannot influence" in bad.message
        assert bad.y_pred[0] == pytest.approx(2.0, abs=1e-12)
        assert np.all(bad.y_pred[2:] <= 1.0 + 1e-9)  # the limits it can meet, it meets
        mv = MPCProblem(delay, (0.5, 4), 20, **kw).move([1.5, 0.0, 0.5], 0.8, u_prev=1.5)
        assert not mv.success and mv.status == -101
        assert mv.du[0] == pytest.approx(bad.du[0], abs=1e-12)

    def test_only_rows_the_inputs_cannot_move(self):
        # the single constrained step is y(k+1) of the delay plant: no QP at all
        delay = ([[0.0, 0.0], [1.0, 0.0]], [1.0, 0.0], [0.0, 1.0])
        problem = MPCProblem(delay, (0.5, 4), 20, r=0.1, y_max=1.0, constraint_steps=1)
        free = MPCProblem(delay, (0.5, 4), 20, r=0.1)
        for x, ok in (([0.0, 0.0, 0.5], True), ([1.5, 0.0, 0.5], False)):
            res, ref = problem.solve(x, 0.8), free.solve(x, 0.8)
            assert res.success is ok and res.status == (0 if ok else -101)
            np.testing.assert_allclose(res.eta, ref.eta, atol=1e-12)
            mv = problem.move(x, 0.8)
            assert mv.success is ok and mv.du[0] == pytest.approx(res.du[0], abs=1e-12)
