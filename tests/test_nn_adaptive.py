"""Adaptive-pole estimator: network poles, least-squares coefficients, trained end to end.

Oracles: the fixed nominal basis (the ceiling the adaptive basis must beat), the
stability region (every predicted pole has Re < 0 for any input), exact
reconstruction from the returned poles and coefficients with the numpy core, and
save/load round trips.
"""

from __future__ import annotations

import copy
import json

import numpy as np
import pytest
import scipy.linalg
import scipy.signal
import torch

import kautztwin as kt
from kautztwin.basis._blocks import parse_poles
from kautztwin.datasets import draw_parameters, make_dataset, paper_system
from kautztwin.exceptions import DataError, DimensionError, NotFittedError
from kautztwin.nn.adaptive import AdaptivePoleEstimator, AdaptivePoleNetwork
from kautztwin.nn.adaptive.training import _match_labels, resolve_relative_degree
from kautztwin.nn.oracle import oracle_fit, simulate_parametric

torch.set_num_threads(1)

SYSTEM = paper_system()
T = np.linspace(0.0, 20.0, 200)
NOMINAL = kt.KautzBasis(SYSTEM.poles())
SMALL = {
    "hidden": (64, 64),
    "n_features": 16,
    "pretrain_epochs": 40,
    "config": {"max_epochs": 3, "batch_size": 128, "learning_rate": 1e-3},
}


@pytest.fixture(scope="module")
def fitted():
    # the constraint explicitly: with 'auto' a network this small may fit without it
    est = AdaptivePoleEstimator(**SMALL, random_state=0, relative_degree=4)
    return est.fit_distribution(SYSTEM, 0.5, T, noise=0.05, n_train=1500)


@pytest.fixture(scope="module")
def test_data():
    P = draw_parameters(SYSTEM, 0.5, 200, random_state=11)
    return make_dataset(SYSTEM, P, NOMINAL, T, noise=0.05, random_state=12)


# --------------------------------------------------------------------------- accuracy
def test_beats_the_fixed_nominal_basis_on_held_out_records(fitted, test_data):
    K = NOMINAL.evaluate(T)
    ceiling = kt.fit_percent(
        test_data.clean, kt.project(NOMINAL, T, test_data.clean, method="lstsq") @ K
    )
    score = fitted.score(test_data)
    # the best any fixed-basis estimator can do (noise-free projection) is about 69 %
    assert np.mean(ceiling) < 75.0
    assert score > np.mean(ceiling) + 15.0


def test_predictions_reconstruct_with_the_numpy_core(fitted, test_data):
    poles, coef = fitted.predict(test_data.responses[:5])
    yhat = fitted.predict_responses(test_data.responses[:5])
    for k in range(5):
        model = kt.KautzModel(kt.KautzBasis(poles[k]), coef[k])
        np.testing.assert_allclose(model.impulse(T), yhat[k], rtol=0, atol=1e-12)


def test_relative_degree_is_read_from_the_training_records(fitted):
    # the paper's system k/((s+a)(s+b)(s^2+2 zeta wn s+wn^2)) has no zeros: relative degree 4
    assert fitted.relative_degree_ == 4
    assert fitted.get_params()["relative_degree"] == 4


def test_coefficients_are_constrained_least_squares_on_the_predicted_basis(fitted, test_data):
    # oracle: least squares over the null space (scipy) of the Markov parameters c^T A^k B,
    # k < 3, of the numpy core's realisation of the predicted basis
    poles, coef = fitted.predict(test_data.responses[:3])
    for k in range(3):
        basis = kt.KautzBasis(poles[k])
        K = basis.evaluate(T)
        A, B = basis.state_space()[:2]
        N = scipy.linalg.null_space(np.stack([B, A @ B, A @ A @ B]))
        ref = N @ np.linalg.lstsq(K.T @ N, test_data.responses[k], rcond=None)[0]
        np.testing.assert_allclose(coef[k], ref, rtol=0, atol=1e-10)
        # the fitted model has relative degree 4: a numerator of degree 0 (scipy's zpk)
        num, den = scipy.signal.ss2tf(A, B[:, None], coef[k][None, :], [[0.0]])
        assert np.max(np.abs(num[0][:-1])) <= 1e-9 * np.max(np.abs(num[0]))
        assert abs(num[0][-1]) > 1e-3


def test_unconstrained_coefficients_are_least_squares_on_the_predicted_basis(fitted, test_data):
    free = copy.deepcopy(fitted)
    free.relative_degree_ = 1  # the plain least squares (relative_degree=1)
    poles, coef = free.predict(test_data.responses[:3])
    for k in range(3):
        K = kt.KautzBasis(poles[k]).evaluate(T)
        ref = np.linalg.lstsq(K.T, test_data.responses[k], rcond=None)[0]
        np.testing.assert_allclose(coef[k], ref, rtol=0, atol=1e-10)


def test_predict_models_match_predict(fitted, test_data):
    models = fitted.predict_models(test_data.responses[:3])
    poles, coef = fitted.predict(test_data.responses[:3])
    assert len(models) == 3
    for m, p, c in zip(models, poles, coef, strict=True):
        np.testing.assert_allclose(m.poles, p, rtol=1e-12)
        np.testing.assert_allclose(m.coefficients, c, rtol=0, atol=1e-14)


def test_one_record_gives_one_dimensional_output(fitted, test_data):
    poles, coef = fitted.predict(test_data.responses[0])
    assert poles.shape == (4,) and coef.shape == (4,)
    assert fitted.predict_responses(test_data.responses[0]).shape == (T.size,)


def test_dataset_input_checks_grid_and_kind(fitted, test_data):
    poles, _ = fitted.predict(test_data)
    assert poles.shape == (200, 4)
    step = make_dataset(SYSTEM, SYSTEM.nominal, NOMINAL, T, kind="step")
    with pytest.raises(DataError, match="step responses"):
        fitted.predict(step)


# --------------------------------------------------------------------------- stability
@pytest.mark.parametrize(
    "records",
    [
        np.random.default_rng(1).standard_normal((50, T.size)),
        1e6 * np.random.default_rng(2).standard_normal((5, T.size)),
        -np.exp(-3 * T)[None, :],
        np.sin(9 * T)[None, :],
    ],
    ids=["white-noise", "huge-scale", "negative-fast", "undamped-sine"],
)
def test_predicted_poles_are_stable_for_any_input(fitted, records):
    poles, coef = fitted.predict(records)
    assert np.all(poles.real < 0)
    assert np.all(np.isfinite(coef))
    # conjugate pairs stay paired: each model builds a valid basis
    for p in poles:
        kt.KautzBasis(p)


def test_poles_stay_within_the_pole_range(fitted):
    poles, _ = fitted.predict(np.random.default_rng(3).standard_normal((100, T.size)))
    centre = np.abs(fitted.centre_poles_.real)
    ratio = np.abs(poles.real) / centre
    assert np.all(ratio <= fitted.pole_range * (1 + 1e-6))
    assert np.all(ratio >= 1 / fitted.pole_range * (1 - 1e-6))


def test_untrained_network_predicts_the_centre_poles():
    centre = np.array([0.5, 1.9, 1.0, 3.0])
    projector = np.linalg.qr(np.random.default_rng(0).standard_normal((T.size, 8)))[0]
    net = AdaptivePoleNetwork(("pair", "real", "real"), centre, T, projector, hidden=(8,))
    x = torch.as_tensor(np.random.default_rng(1).standard_normal((3, T.size)), dtype=torch.float32)
    expected = torch.as_tensor(centre, dtype=torch.float32).expand(3, -1)
    torch.testing.assert_close(net(x), expected)


# --------------------------------------------------------------------------- refinement
def test_refine_does_not_increase_the_record_residual(fitted, test_data):
    X = test_data.responses[:3]
    plain = fitted.predict_responses(X)
    refined = fitted.predict_responses(X, refine=True)
    r_plain = np.linalg.norm(X - plain, axis=1)
    r_refined = np.linalg.norm(X - refined, axis=1)
    assert np.all(r_refined <= r_plain * (1 + 1e-6))
    assert np.all(fitted.predict(X, refine=True)[0].real < 0)


# --------------------------------------------------------------------------- structure
def test_structure_as_block_kinds():
    options = {**SMALL, "pretrain_epochs": 0, "config": {"max_epochs": 1}}
    est = AdaptivePoleEstimator(**options, structure=("pair", "real"))
    data = make_dataset(SYSTEM, draw_parameters(SYSTEM, 0.3, 60, random_state=0), NOMINAL, T)
    est.fit(data)
    assert est.kinds_ == ("pair", "real")
    poles, coef = est.predict(data.responses[:2])
    assert poles.shape == (2, 3) and coef.shape == (2, 3)


def test_structure_as_poles_sets_the_centre():
    start = [-0.4 + 2j, -0.4 - 2j, -1.5]
    options = {**SMALL, "pretrain_epochs": 0, "config": {"max_epochs": 1}}
    est = AdaptivePoleEstimator(**options, structure=start)
    data = make_dataset(SYSTEM, draw_parameters(SYSTEM, 0.3, 40, random_state=0), NOMINAL, T)
    est.fit(data)
    np.testing.assert_allclose(est.centre_poles_, kt.KautzBasis(start).poles, rtol=1e-6)


def test_match_labels_orders_blocks_by_rate():
    kinds, centre = ("real", "pair", "real"), np.array([3.0, 0.5, 2.0, 1.0])
    poles = np.array([[-0.4 + 1j, -0.4 - 1j, -0.9, -2.5], [-1, -2, -3, -4]], dtype=complex)
    labels, valid = _match_labels(kinds, centre, poles)
    np.testing.assert_allclose(labels[0], [2.5, 0.4, 1.0, 0.9])
    assert valid.tolist() == [True, False]


def test_step_records():
    options = {**SMALL, "pretrain_epochs": 5, "config": {"max_epochs": 1}}
    est = AdaptivePoleEstimator(**options).fit_distribution(
        SYSTEM, 0.3, T, noise=0.02, n_train=300, kind="step"
    )
    assert est.kind_ == "step"
    data = make_dataset(SYSTEM, SYSTEM.nominal, NOMINAL, T, kind="step", noise=0.02, random_state=3)
    (model,) = est.predict_models(data)
    assert np.all(model.poles.real < 0)
    np.testing.assert_allclose(model.step(T), est.predict_responses(data)[0], rtol=0, atol=1e-10)


@pytest.mark.parametrize(
    ("zeros", "expected"), [([], 4), ([-2.0], 3), ([-2.0, -0.7], 2), ([-2.0, -0.7, -5.0], 1)]
)
def test_auto_relative_degree_is_poles_minus_zeros(zeros, expected):
    # oracle: the relative degree of k prod(s - z) / prod(s - p) is #poles - #zeros
    system = kt.datasets.ParametricSystem.from_zpk(zeros, SYSTEM.poles(), 6.0)
    data = make_dataset(system, draw_parameters(system, 0.3, 30, random_state=2), NOMINAL, T)
    kinds, centre = parse_poles(NOMINAL.poles, 0.0)
    labels, valid = _match_labels(kinds, centre, np.asarray(data.poles))
    assert valid.all()
    got = resolve_relative_degree("auto", kinds, T, data.clean, "impulse", labels, valid)
    assert got == expected
    step = make_dataset(system, draw_parameters(system, 0.3, 5, random_state=3), NOMINAL, T,
                        kind="step")
    labels, valid = _match_labels(kinds, centre, np.asarray(step.poles))
    assert resolve_relative_degree("auto", kinds, T, step.clean, "step", labels, valid) == expected
    # no record whose poles fit the structure: no constraint
    assert resolve_relative_degree("auto", kinds, T, data.clean, "impulse", labels,
                                   np.zeros_like(valid)) == 1


def test_auto_keeps_the_constraint_only_where_the_poles_are_precise():
    # an untrained network predicts the centre poles; records of the nominal system (whose
    # poles are the centre) are fitted better with the constraint, records under +-50 %
    # uncertainty (centre poles far off) better without it
    est = AdaptivePoleEstimator(hidden=(4,), n_features=4, n_stages=1, pretrain_epochs=0,
                                config={"max_epochs": 1, "learning_rate": 1e-12},
                                relative_degree="auto")
    nominal = make_dataset(SYSTEM, np.tile(SYSTEM.nominal, (60, 1)), NOMINAL, T, noise=0.1,
                           random_state=4)
    wide = make_dataset(SYSTEM, draw_parameters(SYSTEM, 0.5, 60, random_state=5), NOMINAL, T,
                        noise=0.01, random_state=6)
    assert est.fit(nominal).relative_degree_ == 4
    assert est.fit(wide).relative_degree_ == 1
    assert est.network_.relative_degree == 4  # the stages keep the degree they trained with
    assert AdaptivePoleEstimator(**{**est.get_params(), "relative_degree": 4}).fit(
        wide).relative_degree_ == 4  # an explicit degree is kept
    # the default is the unconstrained fit
    assert AdaptivePoleEstimator(hidden=(4,), n_features=4, n_stages=1, pretrain_epochs=0,
                                 config={"max_epochs": 1, "learning_rate": 1e-12}).fit(
        nominal).relative_degree_ == 1


def test_relative_degree_option_is_used_and_kept_by_files(tmp_path):
    data = make_dataset(SYSTEM, draw_parameters(SYSTEM, 0.3, 40, random_state=0), NOMINAL, T,
                        noise=0.05, random_state=1)
    est = AdaptivePoleEstimator(hidden=(8,), n_features=4, pretrain_epochs=0,
                                config={"max_epochs": 1}, relative_degree=2).fit(data)
    assert est.relative_degree_ == 2
    loaded = AdaptivePoleEstimator.load(est.save(tmp_path / "m"))
    assert loaded.relative_degree_ == 2 and loaded.relative_degree == 2
    np.testing.assert_array_equal(loaded.predict(data)[1], est.predict(data)[1])
    # a file written before the option (no relative_degree in its architecture) loads as 1
    meta = json.loads((tmp_path / "m" / "metadata.json").read_text())
    del meta["architecture"]["relative_degree"], meta["fit_relative_degree"]
    from kautztwin.nn.model_files import save_verified  # rewrite with valid checksums

    state = torch.load(tmp_path / "m" / "weights.pt", weights_only=True)
    header = ("format", "format_version", "kautztwin_version", "torch_version", "time_grid",
              "weights", "metadata_sha256")
    fields = {k: v for k, v in meta.items() if k not in header}
    save_verified(tmp_path / "old", meta["format"], meta["format_version"], state,
                  np.asarray(est.t_), fields)
    assert AdaptivePoleEstimator.load(tmp_path / "old").relative_degree_ == 1


def test_network_is_kept_in_float64_and_fine_tunes_in_float32(fitted, test_data):
    assert fitted.network_.dtype == torch.float64
    tuned = fitted.fine_tune(test_data, config={"max_epochs": 1})
    assert tuned.network_.dtype == torch.float64 and fitted.network_.dtype == torch.float64
    assert tuned.relative_degree_ == fitted.relative_degree_


# --------------------------------------------------------------------------- files
def test_save_load_round_trip(fitted, test_data, tmp_path):
    fitted.save(tmp_path / "m")
    loaded = AdaptivePoleEstimator.load(tmp_path / "m")
    p0, c0 = fitted.predict(test_data.responses[:10])
    p1, c1 = loaded.predict(test_data.responses[:10])
    np.testing.assert_array_equal(p0, p1)
    np.testing.assert_array_equal(c0, c1)
    assert loaded.kinds_ == fitted.kinds_
    assert [h.train_loss for h in loaded.histories_] == [h.train_loss for h in fitted.histories_]
    np.testing.assert_array_equal(loaded.t_, fitted.t_)


def test_load_detects_modified_files(fitted, tmp_path):
    d = fitted.save(tmp_path / "m")
    meta = json.loads((d / "metadata.json").read_text())
    meta["kind"] = "step"
    (d / "metadata.json").write_text(json.dumps(meta))
    with pytest.raises(DataError, match="checksum mismatch"):
        AdaptivePoleEstimator.load(d)
    d2 = fitted.save(tmp_path / "m2")
    with (d2 / "weights.pt").open("ab") as fh:
        fh.write(b"\0")
    with pytest.raises(DataError, match="checksum mismatch"):
        AdaptivePoleEstimator.load(d2)
    with pytest.raises(DataError, match="does not exist"):
        AdaptivePoleEstimator.load(tmp_path / "missing")


# --------------------------------------------------------------------------- errors
def test_wrong_length_is_rejected(fitted):
    with pytest.raises(DimensionError, match="199 samples per record"):
        fitted.predict(np.ones((2, 199)))
    with pytest.raises(DimensionError, match="1-D"):
        fitted.predict(np.ones((2, 2, T.size)))


def test_non_finite_values_are_rejected(fitted):
    X = np.ones((3, T.size))
    X[1, 7] = np.nan
    with pytest.raises(DataError, match="record 1, sample 7"):
        fitted.predict(X)


def test_all_zero_record_is_rejected(fitted):
    with pytest.raises(DataError, match="all zeros"):
        fitted.predict(np.zeros(T.size))


def test_other_grid_is_rejected(fitted):
    with pytest.raises(DataError, match="training grid"):
        fitted.predict(np.ones(T.size), t=T * 2)


def test_not_fitted():
    with pytest.raises(NotFittedError, match="not fitted"):
        AdaptivePoleEstimator().predict(np.ones(T.size))


@pytest.mark.parametrize(
    ("option", "match"),
    [
        ({"hidden": (0,)}, "hidden"),
        ({"n_features": 0}, "n_features"),
        ({"pole_range": 1.0}, "pole_range"),
        ({"weights": "trapezoid"}, "weights"),
        ({"random_state": -1}, "random_state"),
        ({"config": 3}, "config"),
        ({"structure": ("real", "triple")}, "block kinds"),
        ({"structure": [0.5, -1.0]}, "structure"),
        ({"pretrain_epochs": -1}, "pretrain_epochs"),
        ({"relative_degree": 0}, "relative_degree"),
        ({"relative_degree": 5}, "at most the number of basis functions"),
        ({"relative_degree": "max"}, "relative_degree"),
    ],
    ids=[
        "hidden",
        "n_features",
        "pole_range",
        "weights",
        "seed",
        "config",
        "kinds",
        "unstable",
        "pretrain",
        "degree-0",
        "degree-too-high",
        "degree-text",
    ],
)
def test_invalid_options(option, match):
    data = make_dataset(SYSTEM, SYSTEM.nominal, NOMINAL, T)
    data = make_dataset(SYSTEM, draw_parameters(SYSTEM, 0.1, 4, random_state=0), NOMINAL, T)
    with pytest.raises(DataError, match=match):
        AdaptivePoleEstimator(**option).fit(data)


def test_fit_rejects_non_dataset():
    with pytest.raises(DataError, match="ResponseDataset"):
        AdaptivePoleEstimator().fit(np.ones((3, 10)))


def test_params_round_trip():
    est = AdaptivePoleEstimator(hidden=(8,), refine=True)
    assert est.get_params()["refine"] is True
    est.set_params(hidden=(16,))
    assert est.hidden == (16,)
    with pytest.raises(DataError, match="invalid parameter"):
        est.set_params(nonsense=1)


# --------------------------------------------------------------------------- oracle
def test_oracle_recovers_noise_free_parameters():
    truth = np.array([5.0, 1.2, 2.5, 1.8, 0.3])
    h = simulate_parametric(SYSTEM, truth, T)
    res = oracle_fit(T, h, SYSTEM, truth * 1.02)
    np.testing.assert_allclose(res.parameters, truth, rtol=1e-6)
    np.testing.assert_allclose(res.response, h, rtol=0, atol=1e-9)


def test_oracle_simulation_matches_make_dataset():
    P = draw_parameters(SYSTEM, 0.5, 3, random_state=4)
    t = np.linspace(0.3, 20.0, 150)
    data = make_dataset(SYSTEM, P, NOMINAL, t)
    for p, clean in zip(P, data.clean, strict=True):
        np.testing.assert_allclose(simulate_parametric(SYSTEM, p, t), clean, rtol=0, atol=1e-13)
    step = make_dataset(SYSTEM, P[:1], NOMINAL, t, kind="step")
    np.testing.assert_allclose(
        simulate_parametric(SYSTEM, P[0], t, kind="step"), step.clean[0], rtol=0, atol=1e-13
    )


def test_oracle_errors():
    with pytest.raises(DataError, match="kind"):
        oracle_fit(T, np.ones(T.size), SYSTEM, SYSTEM.nominal, kind="ramp")
    with pytest.raises(DimensionError, match="one 1-D record"):
        oracle_fit(T, np.ones((2, T.size)), SYSTEM, SYSTEM.nominal)
    with pytest.raises(DimensionError, match="5 entries"):
        oracle_fit(T, np.ones(T.size), SYSTEM, [1.0, 2.0])


# --------------------------------------------------------------------------- slow
@pytest.mark.slow
def test_close_to_the_oracle_at_one_percent_noise():
    t = np.linspace(0.0, 20.0, 900)
    est = AdaptivePoleEstimator(random_state=0).fit_distribution(
        SYSTEM, 0.5, t, noise=0.01, n_train=20000
    )
    P = draw_parameters(SYSTEM, 0.5, 100, random_state=21)
    data = make_dataset(SYSTEM, P, NOMINAL, t, noise=0.01, random_state=22)
    adaptive = kt.fit_percent(data.clean, est.predict_responses(data))
    oracle = [
        kt.fit_percent(c, oracle_fit(t, y, SYSTEM, p).response)
        for c, y, p in zip(data.clean, data.responses, P, strict=True)
    ]
    assert np.mean(oracle) - np.mean(adaptive) < 0.5


def test_uncertainty_of_a_constrained_fit_is_lifted_to_the_coefficients(fitted, test_data):
    # the Laplace covariance is computed in (poles, free coefficient directions) and lifted to
    # (poles, Kautz coefficients); the band recomputed from the lifted covariance on the same
    # grid (numpy core Jacobian, Kautz coefficient coordinates) must give the same std
    res = fitted.estimate(test_data.responses[:2])
    assert res.covariance.shape == (2, 8, 8)
    for i in range(2):
        band = res.impulse_band(i, t=T + 0.0)
        np.testing.assert_allclose(band.std, res.std[i], rtol=1e-4, atol=1e-9 * res.std[i].max())
