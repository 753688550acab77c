"""Fine-tuning of the neural estimators: a new estimator from the old weights, on new data.

Oracles: the original estimator is bitwise unchanged; with a vanishing learning
rate the new networks equal the old ones (so the run starts from them); around a
shifted operating point the fine-tuned estimator beats the old one and a network
trained from scratch with the same short budget.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

import kautztwin as kt
from kautztwin.datasets import ParametricSystem, draw_parameters, make_dataset, paper_system
from kautztwin.exceptions import DataError, NotFittedError
from kautztwin.metrics import fit_percent
from kautztwin.nn import (
    AdaptivePoleEstimator,
    CoefficientEstimator,
    TrainingConfig,
    TrainingHistory,
)

torch.set_num_threads(1)

SYSTEM = paper_system()
T = np.linspace(0.0, 20.0, 100)
OLD_BASIS = kt.KautzBasis(SYSTEM.poles())
# the new operating point: lower gain, slower poles, less damping
SHIFTED = ParametricSystem(
    "shifted", SYSTEM.parameter_names, [4.0, 0.6, 2.0, 1.4, 0.35], SYSTEM.builder
)
NEW_BASIS = kt.KautzBasis(SHIFTED.poles())
ZERO_LR = {"max_epochs": 1, "learning_rate": 1e-12}  # Adam steps of at most ~1e-12


def _data(system, basis, n, seed, *, t=T, kind="impulse"):
    P = draw_parameters(system, 0.2, n, random_state=seed)
    return make_dataset(system, P, basis, t, kind=kind, noise=0.05, random_state=seed + 1)


def _mean_fit(est, data):
    models = est.predict_models(data)
    yhat = np.array([m.impulse(data.t) for m in models])
    return float(np.mean(fit_percent(data.clean, yhat)))


def _weights(est):
    return {k: v.clone() for k, v in est._state().items()}


@pytest.fixture(scope="module")
def old_data():
    return _data(SYSTEM, OLD_BASIS, 150, 0)


@pytest.fixture(scope="module")
def new_data():
    return _data(SHIFTED, NEW_BASIS, 60, 2)


@pytest.fixture(scope="module")
def held_out():
    return _data(SHIFTED, NEW_BASIS, 100, 4)


@pytest.fixture(scope="module")
def multi_output(old_data):
    config = {"max_epochs": 20, "batch_size": 32}
    return CoefficientEstimator(per_coefficient=False, config=config).fit(old_data)


@pytest.fixture(scope="module")
def per_coefficient(old_data):
    return CoefficientEstimator(config={"max_epochs": 2, "batch_size": 32}).fit(old_data)


# --------------------------------------------------------------------------- CoefficientEstimator
def test_fine_tune_leaves_the_original_unchanged(multi_output, new_data):
    before = _weights(multi_output)
    scalers = (multi_output.input_scaler_, multi_output.label_scaler_)
    config, histories = multi_output.config_, list(multi_output.histories_)
    new = multi_output.fine_tune(new_data, config={"max_epochs": 2})
    after = _weights(multi_output)
    assert before.keys() == after.keys()
    for name, tensor in before.items():
        torch.testing.assert_close(after[name], tensor, rtol=0, atol=0)
    assert multi_output.input_scaler_ is scalers[0] and multi_output.label_scaler_ is scalers[1]
    assert multi_output.config_ == config and multi_output.histories_ == histories
    assert multi_output.basis_.allclose(OLD_BASIS)
    assert new is not multi_output
    assert all(a is not b for a, b in zip(new.networks_, multi_output.networks_, strict=True))


def test_fine_tuned_estimator_takes_the_new_basis_and_refits_the_scalers(multi_output, new_data):
    new = multi_output.fine_tune(new_data, config={"max_epochs": 2})
    assert new.basis_.allclose(NEW_BASIS)
    assert new.n_functions_ == 4 and new.kind_ == "impulse"
    np.testing.assert_array_equal(new.t_, multi_output.t_)
    assert not np.allclose(new.label_scaler_.mean, multi_output.label_scaler_.mean)
    assert len(new.histories_) == 1 and new.histories_[0].n_epochs <= 2
    assert new.get_params()["per_coefficient"] is False


@pytest.mark.parametrize("variant", ["multi_output", "per_coefficient"])
def test_fine_tune_starts_from_the_trained_weights(request, variant, old_data):
    est = request.getfixturevalue(variant)
    # same data and seed: same split and scalers, so only the weights could differ
    new = est.fine_tune(old_data, config=ZERO_LR)
    old_w, new_w = _weights(est), _weights(new)
    assert old_w.keys() == new_w.keys()
    for name, tensor in old_w.items():
        torch.testing.assert_close(new_w[name], tensor, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        new.predict(old_data.responses[:20]),
        est.predict(old_data.responses[:20]),
        rtol=1e-6,
        atol=1e-9,
    )


def test_default_config_is_a_short_gentle_run(multi_output):
    new_cfg = multi_output.fine_tune(
        _data(SYSTEM, OLD_BASIS, 20, 7), config={"max_epochs": 1}
    ).config_
    assert new_cfg.max_epochs == 1
    assert new_cfg.learning_rate == pytest.approx(multi_output.config_.learning_rate / 3)
    full = TrainingConfig.preset("paper", max_epochs=3)
    assert multi_output.fine_tune(_data(SYSTEM, OLD_BASIS, 20, 7), config=full).config_ == full


def test_default_config_derives_from_the_original(monkeypatch, multi_output, new_data):
    seen = {}

    def spy(module, train, val, loss_fn, config, **kwargs):
        seen["config"] = config
        return TrainingHistory((1.0,), (1.0,), 0, 0.0, False)

    monkeypatch.setattr("kautztwin.nn.coefficient.training.fit_network", spy)
    new = multi_output.fine_tune(new_data)
    base = multi_output.config_
    assert seen["config"] == new.config_
    assert new.config_.max_epochs == int(np.ceil(base.max_epochs / 4))  # 20 -> 5
    assert new.config_.learning_rate == pytest.approx(base.learning_rate / 3)
    assert new.config_.batch_size == base.batch_size


def test_fine_tune_improves_the_fit_around_a_shifted_operating_point(
    multi_output, new_data, held_out
):
    new = multi_output.fine_tune(new_data, config={"max_epochs": 5})
    scratch = CoefficientEstimator(per_coefficient=False, config=new.config_).fit(new_data)
    old_fit, new_fit = _mean_fit(multi_output, held_out), _mean_fit(new, held_out)
    scratch_fit = _mean_fit(scratch, held_out)
    # measured: old 35.4 %, fine-tuned 81.1 %, from scratch with the same budget 69.7 %
    assert new_fit > old_fit + 30.0
    assert new_fit > scratch_fit + 5.0


def test_fine_tune_is_deterministic(multi_output, new_data):
    a = multi_output.fine_tune(new_data, config={"max_epochs": 2}, random_state=3)
    b = multi_output.fine_tune(new_data, config={"max_epochs": 2}, random_state=3)
    assert a.random_state == 3
    np.testing.assert_array_equal(a.predict(new_data), b.predict(new_data))


def test_fine_tune_keeps_basis_poles_consistent(old_data, new_data):
    est = CoefficientEstimator(
        basis_poles=OLD_BASIS.poles, per_coefficient=False, config={"max_epochs": 1}
    ).fit(old_data)
    new = est.fine_tune(new_data, config={"max_epochs": 1})
    assert kt.KautzBasis(new.basis_poles).allclose(NEW_BASIS)
    new.set_params(random_state=1).fit(new_data)  # its parameters describe the new basis


@pytest.mark.parametrize(
    ("data", "match"),
    [
        (
            lambda: _data(SHIFTED, NEW_BASIS, 10, 5, t=np.linspace(0.0, 20.0, 90)),
            "t has 90 samples",
        ),
        (
            lambda: _data(SHIFTED, NEW_BASIS, 10, 5, t=np.linspace(0.0, 25.0, 100)),
            "differs from the training grid",
        ),
        (
            lambda: _data(SHIFTED, kt.KautzBasis([-0.6, -2.0, -1.0]), 10, 5),
            "labelled with 3 Kautz coefficients but the estimator predicts 4",
        ),
        (
            lambda: _data(SHIFTED, NEW_BASIS, 10, 5, kind="step"),
            "holds step responses but the estimator was trained on impulse",
        ),
        (lambda: "records", "must be a kautztwin.datasets.ResponseDataset"),
    ],
    ids=["length", "grid", "n_functions", "kind", "type"],
)
def test_fine_tune_rejects_mismatched_data(multi_output, data, match):
    with pytest.raises(DataError, match=match):
        multi_output.fine_tune(data())


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"config": "fast"}, "config must be a TrainingConfig"),
        ({"config": {"epochs": 3}}, "unknown training option"),
        ({"random_state": -1}, "random_state must be a non-negative integer"),
    ],
    ids=["config-type", "config-key", "seed"],
)
def test_fine_tune_rejects_bad_options(multi_output, new_data, kwargs, match):
    with pytest.raises(DataError, match=match):
        multi_output.fine_tune(new_data, **kwargs)


def test_fine_tune_needs_a_fitted_estimator(new_data):
    with pytest.raises(NotFittedError, match="not fitted"):
        CoefficientEstimator().fine_tune(new_data)


def test_fine_tuned_estimator_saves_and_loads(multi_output, new_data, held_out, tmp_path):
    new = multi_output.fine_tune(new_data, config={"max_epochs": 2})
    loaded = CoefficientEstimator.load(new.save(tmp_path / "tuned"))
    assert loaded.basis_.allclose(NEW_BASIS) and loaded.config_ == new.config_
    np.testing.assert_array_equal(loaded.predict(held_out), new.predict(held_out))


# --------------------------------------------------------------------------- AdaptivePoleEstimator
@pytest.fixture(scope="module")
def adaptive(old_data):
    est = AdaptivePoleEstimator(
        hidden=(32, 32),
        n_features=12,
        n_stages=1,
        pretrain_epochs=20,
        config={"max_epochs": 3},
    )
    return est.fit(old_data)


def test_adaptive_fine_tune_leaves_the_original_unchanged(adaptive, new_data):
    before = {k: v.clone() for k, v in adaptive.network_.state_dict().items()}
    new = adaptive.fine_tune(new_data, config={"max_epochs": 1})
    for name, tensor in adaptive.network_.state_dict().items():
        torch.testing.assert_close(tensor, before[name], rtol=0, atol=0)
    assert new.network_ is not adaptive.network_
    assert new.pretrain_histories_ == [] and len(new.histories_) == 1


def test_adaptive_fine_tune_starts_from_the_trained_weights(adaptive, new_data, held_out):
    # the normalisation is kept, so a vanishing step leaves every prediction as it was
    new = adaptive.fine_tune(new_data, config=ZERO_LR)
    for name, tensor in adaptive.network_.state_dict().items():
        torch.testing.assert_close(new.network_.state_dict()[name], tensor, rtol=0, atol=1e-9)
    np.testing.assert_allclose(
        new.predict_responses(held_out),
        adaptive.predict_responses(held_out),
        rtol=1e-6,
        atol=1e-8,
    )


def test_adaptive_fine_tune_improves_the_fit_around_a_shifted_operating_point(adaptive, held_out):
    data = _data(SHIFTED, NEW_BASIS, 150, 8)
    new = adaptive.fine_tune(data, config={"max_epochs": 5, "learning_rate": 1e-3})
    # measured: 71.5 % -> 92.2 %
    assert adaptive.score(held_out) > 60.0
    assert new.score(held_out) > adaptive.score(held_out) + 5.0


def test_adaptive_fine_tune_rejects_mismatched_data(adaptive):
    with pytest.raises(DataError, match="t has shape"):
        adaptive.fine_tune(_data(SHIFTED, NEW_BASIS, 10, 5, t=np.linspace(0.0, 20.0, 90)))
    with pytest.raises(DataError, match="holds step responses"):
        adaptive.fine_tune(_data(SHIFTED, NEW_BASIS, 10, 5, kind="step"))
    with pytest.raises(NotFittedError, match="not fitted"):
        AdaptivePoleEstimator().fine_tune(_data(SHIFTED, NEW_BASIS, 10, 5))
