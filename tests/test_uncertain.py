"""Uncertain-system data sets: parametric models, parameter draws, labelled responses."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import scipy.signal

import kautztwin as kt
from kautztwin.data import reference_system
from kautztwin.datasets import (
    ParametricSystem,
    ResponseDataset,
    draw_parameters,
    factorial_parameters,
    make_dataset,
    paper_system,
)
from kautztwin.exceptions import DataError, DimensionError

W = np.sqrt(15.0) / 2.0
PAPER_POLES = np.array([-0.5 + 1j * W, -0.5 - 1j * W, -1.0, -3.0])  # the documented sort order
PAPER_DEN = np.array([1.0, 5.0, 11.0, 19.0, 12.0])
NAMES = ("k", "a", "b", "wn", "zeta")
NOMINAL = np.array([6.0, 1.0, 3.0, 2.0, 0.25])


@pytest.fixture(scope="module")
def system():
    return paper_system()


@pytest.fixture(scope="module")
def basis():
    return kt.KautzBasis(PAPER_POLES)


# --------------------------------------------------------------------------- systems
def test_paper_system_nominal_is_exact(system):
    num, den = system.transfer_function()
    assert system.parameter_names == NAMES
    np.testing.assert_array_equal(system.nominal, NOMINAL)
    np.testing.assert_array_equal(num, [6.0])
    np.testing.assert_array_equal(den, PAPER_DEN)  # every operation is exact in binary
    assert system.order == 4


def test_paper_system_poles_sorted_dominant_first(system):
    # np.roots is an eigenvalue solve: rounding level of the coefficients (about 1e-15)
    np.testing.assert_allclose(system.poles(), PAPER_POLES, rtol=0, atol=1e-13)


def test_paper_system_matches_reference_system(system):
    ref = reference_system()
    num, den = system.transfer_function()
    np.testing.assert_array_equal(den, ref.den)
    np.testing.assert_array_equal(num, ref.num)


def test_from_zpk_parameters_and_nominal():
    sys = ParametricSystem.from_zpk([-2.0], PAPER_POLES[::-1], 3.0)
    assert sys.parameter_names == (
        "gain", "zero0_rate", "pole0_rate", "pole1_rate", "pole2_wn", "pole2_zeta",
    )  # fmt: skip
    # wn = |p| = 2 and zeta = 0.5 / |p| = 0.25 up to the rounding of sqrt(15)/2
    np.testing.assert_allclose(sys.nominal, [3.0, 2.0, 3.0, 1.0, 2.0, 0.25], rtol=1e-15)
    num, den = sys.transfer_function()
    np.testing.assert_allclose(num, [3.0, 6.0], rtol=1e-15)
    np.testing.assert_allclose(den, PAPER_DEN, rtol=1e-14)


def test_from_zpk_pair_parameters_move_the_pair():
    sys = ParametricSystem.from_zpk([], [-1 + 2j, -1 - 2j], 1.0)
    wn, zeta = np.sqrt(5.0), 1 / np.sqrt(5.0)
    np.testing.assert_allclose(sys.nominal, [1.0, wn, zeta], rtol=1e-15)
    p = sys.poles([1.0, 2 * wn, zeta])  # doubling wn doubles the pole at fixed damping
    np.testing.assert_allclose(p, [-2 + 4j, -2 - 4j], rtol=1e-14)


def test_from_transfer_function_normalises_and_names():
    sys = ParametricSystem.from_transfer_function([0.0, 2.0, 4.0], 2 * PAPER_DEN)
    assert sys.parameter_names == ("num0", "num1", "den1", "den2", "den3", "den4")
    np.testing.assert_array_equal(sys.nominal, [1.0, 2.0, 5.0, 11.0, 19.0, 12.0])
    num, den = sys.transfer_function()
    np.testing.assert_array_equal(num, [1.0, 2.0])
    np.testing.assert_array_equal(den, PAPER_DEN)


def test_from_physical_calls_builder_with_keywords():
    sys = ParametricSystem.from_physical({"k": 2.0, "tau": 0.5}, lambda k, tau: ([k], [tau, 1.0]))
    num, den = sys.transfer_function([4.0, 0.25])
    np.testing.assert_array_equal(num, [16.0])
    np.testing.assert_array_equal(den, [1.0, 4.0])


def test_is_stable_flags_rows(system):
    P = np.array([NOMINAL, [6.0, -1.0, 3.0, 2.0, 0.25], [6.0, 1.0, 3.0, 2.0, -0.1]])
    np.testing.assert_array_equal(system.is_stable(P), [True, False, False])


def test_system_is_frozen(system):
    with pytest.raises(dataclasses.FrozenInstanceError):
        system.name = "other"
    with pytest.raises(ValueError, match="read-only"):
        system.nominal[0] = 1.0


# --------------------------------------------------------------------------- draws
def test_draws_within_bounds_and_cover_them(system):
    u = {"k": 0.1, "a": 0.2, "zeta": 0.5}
    P = draw_parameters(system, u, 2000, random_state=0)
    assert P.shape == (2000, 5)
    for j, name in enumerate(NAMES):
        uj = u.get(name, 0.0)
        lo, hi = NOMINAL[j] * (1 - uj), NOMINAL[j] * (1 + uj)
        assert P[:, j].min() >= lo and P[:, j].max() <= hi
        if uj:
            # 2000 uniform draws: the extreme gaps exceed 0.5 % of the band with prob. 2 e^-10
            assert P[:, j].min() < lo + 0.005 * (hi - lo)
            assert P[:, j].max() > hi - 0.005 * (hi - lo)
        else:
            np.testing.assert_array_equal(P[:, j], NOMINAL[j])


def test_draws_are_reproducible_and_seed_dependent(system):
    a = draw_parameters(system, 0.1, 10, random_state=3)
    b = draw_parameters(system, 0.1, 10, random_state=3)
    c = draw_parameters(system, 0.1, 10, random_state=4)
    np.testing.assert_array_equal(a, b)
    assert not np.allclose(a, c)


def test_zero_uncertainty_gives_nominal(system):
    P = draw_parameters(system, 0.0, 4, random_state=0)
    np.testing.assert_array_equal(P, np.tile(NOMINAL, (4, 1)))
    np.testing.assert_array_equal(factorial_parameters(system, 0.0), NOMINAL[None, :])


def test_unstable_draws_are_redrawn(system):
    # a uniform in [-1, 3]: a quarter of first draws are unstable and must be replaced
    P = draw_parameters(system, {"a": 2.0}, 400, random_state=0)
    assert P[:, 1].min() > 0
    assert system.is_stable(P).all()


def test_factorial_grid_size_and_contents(system):
    P = factorial_parameters(system, 0.1, levels=3)
    assert P.shape == (3**5, 5)
    assert np.unique(P, axis=0).shape[0] == 3**5
    for j in range(5):
        values, counts = np.unique(P[:, j], return_counts=True)
        np.testing.assert_allclose(values, NOMINAL[j] * np.array([0.9, 1.0, 1.1]), rtol=1e-15)
        np.testing.assert_array_equal(counts, [3**4] * 3)


def test_factorial_grid_order_and_fixed_parameters(system):
    P = factorial_parameters(system, {"a": 0.5, "zeta": 0.2}, levels=2)
    expected = np.tile(NOMINAL, (4, 1))
    expected[:, 1] = [0.5, 0.5, 1.5, 1.5]  # first varied parameter slowest
    expected[:, 4] = [0.2, 0.3, 0.2, 0.3]
    np.testing.assert_allclose(P, expected, rtol=1e-15)


# --------------------------------------------------------------------------- dataset
def test_clean_impulse_matches_scipy(system, basis):
    t = np.linspace(0, 20, 901)
    P = draw_parameters(system, 0.2, 3, random_state=1)
    ds = make_dataset(system, P, basis, t)
    for i in range(3):
        _, h = scipy.signal.impulse(system.transfer_function(P[i]), T=t)
        # both exact matrix-exponential solutions; peak |h| is about 0.3
        np.testing.assert_allclose(ds.clean[i], h, rtol=0, atol=1e-12)


def test_clean_step_matches_scipy(system, basis):
    t = np.linspace(0, 20, 901)
    P = draw_parameters(system, 0.2, 3, random_state=2)
    ds = make_dataset(system, P, basis, t, kind="step")
    for i in range(3):
        _, y = scipy.signal.step(system.transfer_function(P[i]), T=t)
        np.testing.assert_allclose(ds.clean[i], y, rtol=0, atol=1e-12)


@pytest.mark.parametrize("kind", ["impulse", "step"])
def test_labels_equal_projection_on_fine_grid(system, basis, kind):
    # independent oracle: Simpson quadrature of the clean record.  Grid step 0.01 s on
    # [0, 40]: Simpson's error ~ T h^4 max|(hK)''''| / 180 ~ 1e-9, and the tail beyond 40 s
    # (decay e^{-0.5 t} for both h and K) ~ e^{-40}; 1e-7 leaves two decades of margin.
    t = np.linspace(0, 40, 4001)
    P = draw_parameters(system, 0.2, 20, random_state=5)
    ds = make_dataset(system, P, basis, t, kind=kind)
    np.testing.assert_allclose(kt.project(basis, t, ds.clean, kind=kind), ds.coefficients,
                               rtol=0, atol=1e-7)


@pytest.mark.parametrize("kind", ["impulse", "step"])
def test_matched_basis_reproduces_clean_response(system, basis, kind):
    # only the gain is uncertain: every record's poles are the basis poles
    t = np.linspace(0, 20, 900)
    P = draw_parameters(system, {"k": 0.3}, 10, random_state=6)
    ds = make_dataset(system, P, basis, t, kind=kind)
    K = basis.evaluate(t) if kind == "impulse" else basis.step_functions(t)
    fit = kt.fit_percent(ds.clean, ds.coefficients @ K)
    assert np.all(fit > 99.9999)


def test_per_record_matched_basis_reproduces_drawn_system(system):
    t = np.linspace(0, 20, 900)
    P = draw_parameters(system, 0.2, 1, random_state=7)
    poles = system.poles(P)[0]
    b = kt.KautzBasis(poles)
    ds = make_dataset(system, P, b, t)
    np.testing.assert_allclose(ds.poles[0], poles, rtol=1e-14)
    assert kt.fit_percent(ds.clean[0], ds.coefficients[0] @ b.evaluate(t)) > 99.9999


def test_dataset_metadata_and_shapes(system, basis):
    t = np.linspace(0, 20, 300)
    P = draw_parameters(system, 0.1, 7, random_state=0)
    ds = make_dataset(system, P, basis, t, noise=0.05, random_state=0)
    assert len(ds) == 7
    assert ds.responses.shape == ds.clean.shape == (7, 300)
    assert ds.coefficients.shape == (7, 4) and ds.poles.shape == (7, 4)
    assert ds.parameter_names == NAMES and ds.kind == "impulse" and ds.noise == 0.05
    np.testing.assert_array_equal(ds.parameters, P)
    np.testing.assert_array_equal(ds.basis_poles, basis.poles)
    assert ds.basis.allclose(basis)
    with pytest.raises(ValueError, match="read-only"):
        ds.responses[0, 0] = 1.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        ds.noise = 0.2


def test_no_noise_gives_clean_responses(system, basis):
    t = np.linspace(0, 20, 200)
    ds = make_dataset(system, NOMINAL, basis, t)
    np.testing.assert_array_equal(ds.responses, ds.clean)


def _normalised_noise(ds):
    return (ds.responses - ds.clean) / np.max(np.abs(ds.clean), axis=1, keepdims=True)


def test_white_noise_std_is_fraction_of_peak(system, basis):
    t = np.linspace(0, 20, 900)
    P = draw_parameters(system, 0.2, 200, random_state=0)
    ds = make_dataset(system, P, basis, t, noise=0.1, random_state=0)
    e = _normalised_noise(ds)
    # 180,000 iid N(0, 0.1^2) values: relative standard error of the sample std is
    # 1/sqrt(2N) = 0.17 %; 1 % is a 6-sigma band
    np.testing.assert_allclose(e.std(), 0.1, rtol=0.01)
    lag1 = np.sum(e[:, 1:] * e[:, :-1]) / np.sum(e[:, :-1] ** 2)
    assert abs(lag1) < 0.01  # standard error 1/sqrt(N) = 0.0024


def test_colored_noise_std_and_autocorrelation(system, basis):
    t = np.linspace(0, 20, 900)
    P = draw_parameters(system, 0.2, 200, random_state=0)
    ds = make_dataset(system, P, basis, t, noise=0.1, noise_kind="colored", color_pole=0.9,
                      random_state=0)
    e = _normalised_noise(ds)
    # AR(1), a = 0.9: effective sample size N (1 - a^2)/(1 + a^2) ~ 19,000, so the relative
    # standard error of the std is ~0.5 %; 3 % is a 6-sigma band
    np.testing.assert_allclose(e.std(), 0.1, rtol=0.03)
    # the lag-1 estimate has standard error sqrt((1 - a^2)/N) ~ 0.001 plus an O(1/900) bias
    lag1 = np.sum(e[:, 1:] * e[:, :-1]) / np.sum(e[:, :-1] ** 2)
    np.testing.assert_allclose(lag1, 0.9, atol=0.01)


def test_noise_is_reproducible_and_seed_dependent(system, basis):
    t = np.linspace(0, 20, 100)
    P = draw_parameters(system, 0.1, 3, random_state=0)
    a = make_dataset(system, P, basis, t, noise=0.1, random_state=1)
    b = make_dataset(system, P, basis, t, noise=0.1, random_state=1)
    c = make_dataset(system, P, basis, t, noise=0.1, random_state=2)
    np.testing.assert_array_equal(a.responses, b.responses)
    assert not np.allclose(a.responses, c.responses)


def test_quantization_gives_multiples_of_step(system, basis):
    t = np.linspace(0, 20, 300)
    P = draw_parameters(system, 0.1, 5, random_state=0)
    q = 0.01
    ds = make_dataset(system, P, basis, t, noise=0.05, quantization=q, random_state=0)
    ratio = ds.responses / q
    np.testing.assert_allclose(ratio, np.round(ratio), rtol=0, atol=1e-9)
    assert ds.quantization == q
    clean_q = make_dataset(system, P, basis, t, quantization=q)
    assert np.max(np.abs(clean_q.responses - clean_q.clean)) <= q / 2 + 1e-12


def test_save_load_round_trip(system, basis, tmp_path):
    t = np.linspace(0, 20, 100)
    P = draw_parameters(system, 0.1, 6, random_state=0)
    for q, kind in ((None, "impulse"), (0.001, "step")):
        ds = make_dataset(system, P, basis, t, kind=kind, noise=0.1, noise_kind="colored",
                          color_pole=0.5, quantization=q, random_state=0)
        path = ds.save(tmp_path / f"ds_{kind}.npz")
        back = ResponseDataset.load(path)
        assert back.allclose(ds, rtol=0, atol=0)  # bitwise: npz stores the float64 arrays
        assert back.quantization == q and back.kind == kind and back.noise_kind == "colored"
        assert back.parameter_names == NAMES
        assert not back.coefficients.flags.writeable


def test_saved_file_needs_no_pickle(system, basis, tmp_path):
    ds = make_dataset(system, NOMINAL, basis, np.linspace(0, 20, 50))
    path = ds.save(tmp_path / "plain.npz")
    with np.load(path, allow_pickle=False) as npz:
        assert all(npz[k].dtype != object for k in npz.files)


def test_split_sizes_disjoint_and_reproducible(system, basis):
    t = np.linspace(0, 20, 50)
    P = draw_parameters(system, 0.1, 40, random_state=0)
    ds = make_dataset(system, P, basis, t)
    train, val = ds.split(0.85, random_state=0)
    assert (len(train), len(val)) == (34, 6)
    rows = {tuple(r) for r in train.parameters}
    assert rows.isdisjoint(tuple(r) for r in val.parameters)
    assert len(rows | {tuple(r) for r in val.parameters}) == 40
    again, _ = ds.split(0.85, random_state=0)
    np.testing.assert_array_equal(again.parameters, train.parameters)
    # labels travel with their records
    idx = [int(np.flatnonzero((P == r).all(axis=1))[0]) for r in val.parameters]
    np.testing.assert_array_equal(val.coefficients, ds.coefficients[idx])


# --------------------------------------------------------------------------- errors
def test_unknown_parameter_name_lists_valid_ones(system):
    with pytest.raises(DataError, match=r"unknown parameter name\(s\) 'q'.*valid names: 'k', 'a'"):
        draw_parameters(system, {"q": 0.1}, 3)
    with pytest.raises(DataError, match="unknown parameter name"):
        factorial_parameters(system, {"omega": 0.1})


@pytest.mark.parametrize("u", [-0.1, {"a": -0.2}, float("nan")], ids=["float", "dict", "nan"])
def test_negative_uncertainty_raises(system, u):
    with pytest.raises(DataError, match=r"uncertainty.* must be a finite number >= 0"):
        draw_parameters(system, u, 3)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"kind": "ramp"}, "kind must be one of 'impulse', 'step'; got 'ramp'"),
        ({"noise_kind": "pink"}, "noise_kind must be one of"),
        ({"noise": -0.1}, "noise must be a finite number >= 0"),
        ({"color_pole": 1.0}, r"color_pole must lie in \(-1, 1\)"),
        ({"quantization": 0.0}, "quantization must be a positive step"),
    ],
    ids=["kind", "noise_kind", "noise", "color_pole", "quantization"],
)
def test_bad_options_raise(system, basis, kwargs, match):
    with pytest.raises(DataError, match=match):
        make_dataset(system, NOMINAL, basis, np.linspace(0, 5, 20), **kwargs)


def test_bad_counts_raise(system):
    with pytest.raises(DataError, match="n must be a positive integer"):
        draw_parameters(system, 0.1, 0)
    with pytest.raises(DataError, match="levels must be an integer >= 2"):
        factorial_parameters(system, 0.1, levels=1)


def test_unstable_nominal_system_raises():
    with pytest.raises(DataError, match=r"nominal system 'zpk' is not stable: pole 1 has Re >= 0"):
        ParametricSystem.from_zpk([], [1.0, -2.0], 1.0)


def test_unpaired_complex_pole_raises():
    with pytest.raises(DataError, match=r"poles\[0\] = -1\+2j has no conjugate partner"):
        ParametricSystem.from_zpk([], [-1 + 2j, -3.0], 1.0)


def test_unstable_factorial_grid_raises(system):
    # a in {-0.5, 1, 2.5}: no redraw for a deterministic grid
    with pytest.raises(DataError, match=r"factorial grid point 0 .*a=-0\.5.* unstable system"):
        factorial_parameters(system, {"a": 1.5})


def test_draws_give_up_after_max_tries(system):
    # P(a < 0) = 1/4 per draw; 500 rows all stable at the first try has probability 0.75^500
    with pytest.raises(DataError, match=r"still unstable after 1 draws.*'a' change sign"):
        draw_parameters(system, {"a": 2.0}, 500, random_state=0, max_tries=1)


def test_unstable_row_in_make_dataset_raises(system, basis):
    P = np.array([NOMINAL, [6.0, -1.0, 3.0, 2.0, 0.25]])
    match = r"parameters\[1\]: 'paper' is not stable .*pole 1 has Re >= 0"
    with pytest.raises(DataError, match=match):
        make_dataset(system, P, basis, np.linspace(0, 5, 20))


def test_wrong_parameter_columns_raise(system, basis):
    with pytest.raises(DimensionError, match=r"parameters must have shape \(n, 5\)"):
        make_dataset(system, np.ones((3, 4)), basis, np.linspace(0, 5, 20))


def test_biproper_system_and_discrete_basis_raise(basis):
    biproper = ParametricSystem.from_zpk([-2.0], [-1.0], 1.0)
    with pytest.raises(DataError, match="biproper"):
        make_dataset(biproper, biproper.nominal, basis, np.linspace(0, 5, 20))
    first = ParametricSystem.from_zpk([], [-1.0], 1.0)
    with pytest.raises(DataError, match="basis must be continuous-time"):
        make_dataset(first, first.nominal, basis.discretize(0.1), np.linspace(0, 5, 20))


def test_load_missing_file_raises(tmp_path):
    with pytest.raises(DataError, match="does not exist"):
        ResponseDataset.load(tmp_path / "nope.npz")


def test_load_garbage_file_raises(tmp_path):
    path = tmp_path / "garbage.npz"
    path.write_bytes(b"this is not a numpy file")
    with pytest.raises(DataError, match="cannot read dataset file") as info:
        ResponseDataset.load(path)
    assert "\n" not in str(info.value)


@pytest.mark.parametrize("suffix", ["npz", "npy"])
def test_load_foreign_numpy_file_raises(tmp_path, suffix):
    path = tmp_path / f"other.{suffix}"
    with path.open("wb") as fh:
        np.savez(fh, x=np.arange(3)) if suffix == "npz" else np.save(fh, np.arange(3))
    with pytest.raises(DataError, match="not a kautztwin ResponseDataset file"):
        ResponseDataset.load(path)


def test_load_malformed_dataset_raises(system, basis, tmp_path):
    ds = make_dataset(system, NOMINAL, basis, np.linspace(0, 5, 20))
    path = ds.save(tmp_path / "ok.npz")
    with np.load(path) as npz:
        data = dict(npz)
    truncated = tmp_path / "missing.npz"
    np.savez(truncated, **{k: v for k, v in data.items() if k != "coefficients"})
    with pytest.raises(DataError, match="malformed: missing 'coefficients'"):
        ResponseDataset.load(truncated)
    data["clean"] = data["clean"][:, :5]
    bad_shape = tmp_path / "shape.npz"
    np.savez(bad_shape, **data)
    with pytest.raises(DataError, match=r"malformed: clean must have shape \(1, 20\)"):
        ResponseDataset.load(bad_shape)


def test_bad_split_fraction_raises(system, basis):
    ds = make_dataset(system, np.tile(NOMINAL, (3, 1)), basis, np.linspace(0, 5, 20))
    with pytest.raises(DataError, match=r"fraction must lie in \(0, 1\)"):
        ds.split(1.0)
    with pytest.raises(DataError, match="empty training or validation set"):
        ds.split(0.9)
