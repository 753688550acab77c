"""Nonlinear Kautz models (issue #13 item 4): filters, exact recovery, initial state, files, errors.

Oracles: scipy.signal.dlsim for the filter bank, numpy's ``discrete_matrices`` for the torch
network, finite differences (gradcheck) for the torch recursion, and known Wiener, Hammerstein
and Volterra truths simulated here that the fits must recover from noise-free data.  The
real-data targets (hydraulic actuator, cascaded tanks) are ``slow`` tests.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import scipy.signal

from kautztwin.basis._blocks import discrete_matrices
from kautztwin.exceptions import DataError, DimensionError
from kautztwin.ident.nonlinear import (
    MLPMap,
    NonlinearKautzEnsemble,
    NonlinearKautzModel,
    PolynomialMap,
    TorchOptions,
    filter_bank_states,
    identify_nonlinear,
    load_nonlinear_model,
)
from kautztwin.ident.nonlinear.filters import (
    bank_matrices,
    poles_from_raw,
    raw_from_poles,
    torch_bank_matrices,
    torch_bank_states,
    torch_poles_params,
)
from kautztwin.metrics import fit_percent

ROOT = Path(__file__).resolve().parents[1]
PAIR = [0.8 * np.exp(0.4j), 0.8 * np.exp(-0.4j)]
TRUTH = [*PAIR, 0.5]


def _sorted(p):
    return np.sort_complex(np.asarray(p))


# --------------------------------------------------------------------------- filters
def test_bank_states_match_dlsim_from_the_level_steady_state():
    poles = [*TRUTH, -0.3, 0.6 * np.exp(1.2j), 0.6 * np.exp(-1.2j)]
    A, B = bank_matrices(poles)
    rng = np.random.default_rng(0)
    v = rng.normal(size=(200, 2))
    levels = [0.4, -1.2]
    X = filter_bank_states(poles, v, levels)
    xss = np.linalg.solve(np.eye(6) - A, B)
    for c, lvl in enumerate(levels):
        _, _, x = scipy.signal.dlsim((A, B[:, None], np.eye(6), np.zeros((6, 1)), 1),
                                     v[:, c:c + 1], x0=xss * lvl)
        np.testing.assert_allclose(X[:, 6 * c:6 * c + 6], x, atol=1e-12)


def test_pole_parametrisation_round_trips():
    poles = [*TRUTH, -0.3]
    kinds, raw = raw_from_poles(poles)
    np.testing.assert_allclose(_sorted(poles_from_raw(kinds, raw)), _sorted(poles), atol=1e-13)


def test_torch_bank_matches_numpy_and_passes_gradcheck():
    import torch  # a test dependency (pyproject: test extra): missing means a broken install
    torch.set_num_threads(1)
    poles = [*TRUTH, -0.3]
    kinds, raw = raw_from_poles(poles)
    raw_t = torch.tensor(raw, dtype=torch.float64, requires_grad=True)
    par = torch_poles_params(kinds, raw_t)
    A, B = torch_bank_matrices(kinds, par)
    An, Bn = discrete_matrices(kinds, par.detach().numpy())
    np.testing.assert_allclose(A.detach().numpy(), An[0], atol=1e-14)
    np.testing.assert_allclose(B.detach().numpy(), Bn[0], atol=1e-14)
    rng = np.random.default_rng(1)
    v = rng.normal(size=(64, 2))
    lvl = np.array([0.3, -0.7])
    X = torch_bank_states(A, B, torch.tensor(v), torch.tensor(lvl))
    np.testing.assert_allclose(X.detach().numpy(), filter_bank_states(poles, v, lvl), atol=1e-12)

    def f(r, lv, vv):
        Am, Bm = torch_bank_matrices(kinds, torch_poles_params(kinds, r))
        return torch_bank_states(Am, Bm, vv, lv)

    args = (raw_t, torch.tensor(lvl[:1], requires_grad=True),
            torch.tensor(v[:8, :1], requires_grad=True))
    assert torch.autograd.gradcheck(f, args, eps=1e-6, atol=1e-6)


def test_adamw_matches_torch_optim_adamw():
    import torch  # a test dependency (pyproject: test extra): missing means a broken install

    from kautztwin.ident.nonlinear.training import _AdamW

    gen = torch.Generator().manual_seed(0)
    target = torch.randn(5, generator=gen, dtype=torch.float64)
    ours = [torch.zeros(5, dtype=torch.float64, requires_grad=True) for _ in range(2)]
    ref = [p.detach().clone().requires_grad_(True) for p in ours]
    opt = _AdamW(torch, [([ours[0]], 0.01), ([ours[1]], 0.0)], lr=0.05)
    opt_ref = torch.optim.AdamW([{"params": [ref[0]], "weight_decay": 0.01},
                                 {"params": [ref[1]], "weight_decay": 0.0}], lr=0.05)
    for _ in range(50):
        for o, params in ((opt, ours), (opt_ref, ref)):
            o.zero_grad()
            sum(((p - target) ** 4).sum() for p in params).backward()
            o.step()
    for a, b in zip(ours, ref, strict=True):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-14)


# --------------------------------------------------------------------------- exact recovery
def _record(n=400, seed=0):
    return np.random.default_rng(seed).normal(size=n)


def test_wiener_polynomial_truth_recovered_exactly():
    u = _record()
    c, a = np.array([1.0, -0.5, 0.3]), np.array([0.2, 1.0, 0.3, -0.1])
    z = filter_bank_states(TRUTH, u) @ c
    y = np.polyval(a[::-1], z)
    fit = identify_nonlinear(u, y, model="wiener", map="poly", degree=3, n_poles=3, n_folds=1)
    m = fit.model.members[0]
    np.testing.assert_allclose(_sorted(m.poles), _sorted(TRUTH), atol=1e-7)
    # the map: the model's projection is an affine image of the true one, and the
    # polynomial composed with it is the true polynomial
    u2 = _record(300, seed=5)
    z2 = filter_bank_states(TRUTH, u2) @ c
    om = m.output_map
    zm = ((m.states(u2, 0.0) - om.in_mean) / om.in_scale) @ om.projection[:, 0]
    alpha, gamma = np.linalg.lstsq(np.column_stack([zm, np.ones_like(zm)]), z2, rcond=None)[0]
    np.testing.assert_allclose(alpha * zm + gamma, z2, atol=1e-7)
    # the fitted polynomial in zm equals the true one at z = alpha zm + gamma
    ym = m.y_mean + m.y_scale * np.polynomial.polynomial.polyval(zm, om.coef)
    np.testing.assert_allclose(ym, np.polyval(a[::-1], alpha * zm + gamma), atol=1e-7)
    np.testing.assert_allclose(m.simulate(u2, 0.0), np.polyval(a[::-1], z2), atol=1e-7)


def _volterra_truth(u, level=0.0):
    X = filter_bank_states(PAIR, u, level)
    return 0.1 + X @ [1.0, -0.4] + 0.5 * X[:, 0] ** 2 - 0.3 * X[:, 0] * X[:, 1] + 0.2 * X[:, 1] ** 2


def _kernel2(sim, n=24, lags=8):
    """Second-order Volterra kernel h2(k1, k2) at the last sample, probed with impulses."""
    def y(ks):
        u = np.zeros(n)
        for k in ks:
            u[n - 1 - k] += 1.0
        return sim(u)[-1]
    h = np.empty((lags, lags))
    for i in range(1, lags + 1):
        for j in range(1, lags + 1):
            h[i - 1, j - 1] = (y([i, j]) - y([i]) - y([j]) + y([])) / (2.0 if i == j else 1.0)
    return h


def test_volterra_kernel_recovered():
    u = _record()
    fit = identify_nonlinear(u, _volterra_truth(u), model="volterra", degree=2, n_poles=2,
                             n_folds=1)
    m = fit.model.members[0]
    np.testing.assert_allclose(_sorted(m.poles), _sorted(PAIR), atol=1e-8)
    np.testing.assert_allclose(_kernel2(lambda v: m.simulate(v, 0.0)), _kernel2(_volterra_truth),
                               atol=1e-8)
    u2 = _record(200, seed=3)
    np.testing.assert_allclose(m.simulate(u2, 0.0), _volterra_truth(u2), atol=1e-8)


def test_hammerstein_polynomial_truth_recovered():
    u = _record() + 0.5

    def truth(v, level=0.5):
        f = lambda x: 0.5 * x + 0.8 * x**2  # noqa: E731
        return filter_bank_states(TRUTH, f(v), f(level)) @ [1.0, -0.5, 0.3] + 0.1

    y = truth(u)
    fit = identify_nonlinear(u, y, model="hammerstein", map="poly", degree=2, n_poles=3,
                             n_folds=1)
    m = fit.model.members[0]
    np.testing.assert_allclose(_sorted(m.poles), _sorted(TRUTH), atol=1e-7)
    np.testing.assert_allclose(m.level, 0.5, atol=1e-6)
    # the static map: steady-state output for constant inputs
    for c in (-1.0, 0.0, 0.7, 2.0):
        np.testing.assert_allclose(m.simulate(np.full(5, c), c)[-1], truth(np.full(5, c), c)[-1],
                                   atol=1e-7)
    u2 = _record(200, seed=4)
    np.testing.assert_allclose(m.simulate(u2, 0.0), truth(u2, 0.0), atol=1e-7)


# --------------------------------------------------------------------------- initial state
def test_level_recovered_from_the_first_outputs():
    u = _record(300)
    fit = identify_nonlinear(u, _volterra_truth(u), model="volterra", n_poles=2, n_folds=1)
    m = fit.model.members[0]
    u2 = _record(100, seed=9)
    y2 = _volterra_truth(u2, level=0.8)
    assert abs(m.fit_level(u2, y2, n_samples=5) - 0.8) < 1e-6
    np.testing.assert_allclose(m.with_fitted_level(u2, y2, 5).simulate(u2), y2, atol=1e-7)
    ens = NonlinearKautzEnsemble((m, m)).with_fitted_level(u2, y2, 5)
    np.testing.assert_allclose(ens.simulate(u2), y2, atol=1e-7)


# --------------------------------------------------------------------------- MLP structures
def test_mlp_wiener_beats_the_best_linear_model_on_a_wiener_system():
    import torch  # noqa: F401  (a test dependency: the MLP structures train in torch)
    u = _record(300)

    def truth(v):
        return np.tanh(1.5 * filter_bank_states(PAIR, v) @ [1.0, -0.4])

    fit = identify_nonlinear(u, truth(u), model="wiener", n_poles=2, n_folds=2, n_seeds=1,
                             options=TorchOptions(n_hidden=8, max_iter=100))
    # the oracle: the best linear Kautz model with as many poles (Volterra of degree 1)
    linear = identify_nonlinear(u, truth(u), model="volterra", degree=1, n_poles=2, n_folds=2)
    u2 = _record(200, seed=7)
    fit_linear = fit_percent(truth(u2), linear.simulate(u2, 0.0))
    assert fit_percent(truth(u2), fit.simulate(u2, 0.0)) > fit_linear + 10.0


def test_mlp_hammerstein_and_wiener_hammerstein_are_seeded_and_save(tmp_path):
    import torch  # noqa: F401  (a test dependency: the MLP structures train in torch)
    u = _record(200)
    y = filter_bank_states(PAIR, np.tanh(u)) @ [1.0, -0.4]
    opts = TorchOptions(max_iter=60, n_hidden=4, n_input_hidden=4)
    for structure in ("hammerstein", "wiener-hammerstein"):
        fit = identify_nonlinear(u, y, model=structure, n_poles=2, n_folds=2, n_seeds=1,
                                 options=opts)
        assert fit.structure == structure and len(fit.model.members) == 2
        assert fit.fit_percent > 70.0
        path = tmp_path / f"{structure}.json"
        fit.model.save(path)
        back = load_nonlinear_model(path)
        np.testing.assert_allclose(back.simulate(u), fit.simulate(u), rtol=1e-12, atol=1e-12)
    again = identify_nonlinear(u, y, model="wiener-hammerstein", n_poles=2, n_folds=2,
                               n_seeds=1, options=opts)
    np.testing.assert_array_equal(again.simulate(u), fit.simulate(u))  # the same seed


def test_auto_chooses_by_cross_validation_and_reports_candidates():
    import torch  # noqa: F401  (a test dependency: the MLP structures train in torch)
    u = _record(240)
    y = _volterra_truth(u)
    fit = identify_nonlinear(u, y, model="auto", n_poles=2, n_folds=2, n_seeds=1,
                             options=TorchOptions(max_iter=30, n_hidden=4, n_input_hidden=4))
    assert {c["structure"] for c in fit.candidates} == {
        "hammerstein", "wiener-hammerstein", "wiener", "volterra"}
    assert fit.structure == "volterra"  # the truth, recovered exactly, wins the CV
    assert fit.cv_fit_percent == max(c["cv_fit_percent"] for c in fit.candidates)


# --------------------------------------------------------------------------- files, maps
def test_model_dict_round_trip_and_allclose():
    mlp = MLPMap([[1.0], [0.5]], [0.0, 0.1], [[2.0, -1.0]], [0.5], [0.2], [1.5])
    poly = PolynomialMap([[0], [2]], np.eye(2), [0.0], [1.0])
    m = NonlinearKautzModel("wiener-hammerstein", [0.9, 0.2], PolynomialMap(
        [[0, 0, 0, 0, 0, 0], [1, 0, 0, 0, 0, 0], [0, 0, 0, 0, 1, 1]], [0.1, 1.0, 0.3],
        np.zeros(6), np.ones(6)), input_map=poly, level=0.3, dt=0.5)
    back = NonlinearKautzModel.from_dict(m.to_dict())
    assert back.allclose(m)
    u = _record(50)
    np.testing.assert_array_equal(back.simulate(u), m.simulate(u))
    assert not back.with_level(0.4).allclose(m)
    np.testing.assert_allclose(mlp(np.array([[0.2]]))[0], 0.5 + 2 * np.tanh(0) - np.tanh(0.1))


def test_importing_the_subpackage_does_not_import_torch():
    code = ("import sys, kautztwin.ident.nonlinear as m; "
            "m.identify_nonlinear; assert 'torch' not in sys.modules, 'torch imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT)


# --------------------------------------------------------------------------- bad input
@pytest.mark.parametrize(
    ("u", "y", "kwargs", "error", "match"),
    [
        (np.ones(100), np.ones(99), {}, DimensionError, "one length"),
        (np.r_[np.nan, np.zeros(99)], np.zeros(100), {}, DataError, "non-finite"),
        (np.zeros(100), np.r_[np.zeros(50), np.inf, np.zeros(49)], {}, DataError, "non-finite"),
        (np.full(100, 2.0), np.arange(100.0), {}, DataError, "constant"),
        (_record(12), _record(12, 1), {"model": "volterra", "n_poles": 4}, DataError,
         "too few"),
        (_record(100), _record(100, 1), {"model": "narx"}, DataError, "model must be one of"),
        (np.ones((100, 2)), np.ones(100), {}, DimensionError, "1-D"),
    ],
    ids=["unequal-lengths", "nan-input", "inf-output", "constant-input", "too-short",
         "unknown-model", "2-d-input"],
)
def test_bad_input_gives_one_line_errors(u, y, kwargs, error, match):
    with pytest.raises(error, match=match) as info:
        identify_nonlinear(u, y, **kwargs)
    assert "\n" not in str(info.value)


def test_bad_model_file_is_a_data_error(tmp_path):
    path = tmp_path / "x.json"
    path.write_text('{"type": "something"}')
    with pytest.raises(DataError, match="no nonlinear Kautz model"):
        load_nonlinear_model(path)


# --------------------------------------------------------------------------- command line
def _cli(capsys, *argv):
    from kautztwin.cli.main import main

    code = main([str(a) for a in argv])
    out = capsys.readouterr()
    return code, out.out, out.err


def test_cli_identify_model_volterra_recovers_the_truth(tmp_path, capsys):
    import json

    u = _record(300)
    y = _volterra_truth(u)
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.column_stack([u, y]), delimiter=",", header="u,y", comments="")
    model_file = tmp_path / "m.json"
    code, out, err = _cli(capsys, "identify", path, "--dt", 1, "--input", "u", "--output", "y",
                          "--model", "volterra", "--order", 2, "--validate-from", 240,
                          "--save-model", model_file, "--json")
    assert (code, err) == (0, "")
    summary = json.loads(out)
    assert summary["structure"] == "volterra" and summary["n_poles"] == 2
    assert summary["validation_fit_percent"] > 99.9  # an exact model of the plant
    back = load_nonlinear_model(model_file)
    np.testing.assert_allclose(_sorted(back.members[0].poles), _sorted(PAIR), atol=1e-6)


@pytest.mark.parametrize(
    ("extra", "match"),
    [(["--zeros", "1"], "--zeros applies to linear"), (["--kind", "step"], "needs an input/out")],
    ids=["zeros", "step-kind"],
)
def test_cli_identify_model_rejects_linear_flags(tmp_path, capsys, extra, match):
    path = tmp_path / "rec.csv"
    u = _record(100)
    np.savetxt(path, np.column_stack([u, u]), delimiter=",", header="u,y", comments="")
    code, out, err = _cli(capsys, "identify", path, "--dt", 1, "--input", "u", "--output", "y",
                          "--model", "volterra", *extra)
    assert code == 2 and match in err and err.count("\n") == 1


# --------------------------------------------------------------------------- real data (slow)
def _actuator():
    d = np.genfromtxt(ROOT / "data" / "hydraulic_actuator" / "actuator.csv", delimiter=",",
                      names=True)
    return d["u"], d["p"]


@pytest.mark.slow
def test_actuator_validation_fit_beats_65_percent():
    # issue #13: >= 65 % on the 512/512 protocol (sysidentpy's NARX: 57.7 %)
    u, y = _actuator()
    fit = identify_nonlinear(u[:512], y[:512], model="wiener-hammerstein", n_poles=2)
    assert fit_percent(y[512:], fit.simulate(u)[512:]) >= 65.0


@pytest.mark.slow
def test_cascaded_tanks_test_rms_below_040():
    # issue #13: test RMS <= 0.40 V, the level fitted to the first 5 test outputs (protocol)
    d = np.genfromtxt(ROOT / "data" / "cascaded_tanks" / "dataBenchmark.csv", delimiter=",",
                      names=True)
    # the structure model='auto' picks (benchmarks/identification_nonlinear.py: 0.293 V)
    fit = identify_nonlinear(d["uEst"], d["yEst"], model="wiener-hammerstein", n_poles=2)
    model = fit.model.with_fitted_level(d["uVal"], d["yVal"], 5)
    assert np.sqrt(np.mean((d["yVal"] - model.simulate(d["uVal"])) ** 2)) <= 0.40


def test_linearize_gives_the_twin_a_kautz_model_of_small_deviations():
    rng = np.random.default_rng(0)
    g = MLPMap(rng.normal(size=(4, 1)), rng.normal(size=4), rng.normal(size=(2, 4)),
               rng.normal(size=2), [0.0], [1.0])
    f = MLPMap(rng.normal(size=(5, 9)), rng.normal(size=5), rng.normal(size=(1, 5)), [0.3],
               np.zeros(9), np.ones(9))
    m = NonlinearKautzModel("wiener-hammerstein", TRUTH, f, input_map=g, u_mean=1.0,
                            u_scale=2.0, y_mean=3.0, y_scale=0.5, dt=0.1)
    u0 = 1.7
    lin = m.linearize(u0)
    assert lin.model.basis.delayed and lin.model.dt == 0.1
    np.testing.assert_allclose(lin.offset, m.simulate(np.full(5, u0), u0)[-1], rtol=1e-12)
    w = rng.normal(size=100)
    base = m.simulate(np.full(100, u0), u0)
    errors = []
    for eps in (1e-2, 1e-3):
        slope_nl = (m.simulate(u0 + eps * w, u0) - base) / eps
        slope_lin = (lin.predict(u0 + eps * w) - lin.offset) / eps
        errors.append(np.abs(slope_nl - slope_lin).max())
    # first-order agreement: the slope error shrinks with the amplitude (second-order terms)
    assert errors[1] < 0.2 * errors[0] and errors[1] < 1e-3


def test_one_standard_error_rule_prefers_the_smaller_model_within_the_noise():
    from kautztwin.ident.nonlinear.selection import _one_standard_error

    def row(n, mse):
        return {"n_parameters": n, "cv_fold_mse": mse, "cv_fit_percent": -float(np.mean(mse))}

    # best mean 0.10, its standard error over 4 folds 0.04: the 0.13 model is within reach
    best = [0.02, 0.18, 0.06, 0.14]
    assert np.isclose(np.std(best, ddof=1) / 2, 0.0365, atol=5e-4)
    assert _one_standard_error([row(50, best), row(10, [0.13] * 4), row(5, [0.3] * 4)]) == 1
    # a clear winner (tiny fold spread) is kept even though it is the biggest
    assert _one_standard_error([row(50, [0.1] * 4), row(10, [0.13] * 4)]) == 0
