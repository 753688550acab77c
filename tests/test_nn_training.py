"""Training loop, presets, 85/15 split and normalisation of kautztwin.nn."""

from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch  # noqa: E402 - the [nn] extra, part of [test]

from kautztwin.exceptions import ConvergenceWarning, DataError, DimensionError  # noqa: E402
from kautztwin.nn import (  # noqa: E402
    Standardizer,
    TrainingConfig,
    TrainingHistory,
    fit_network,
    split_indices,
)

torch.set_num_threads(1)


def mse(module, batch):
    return torch.nn.functional.mse_loss(module(batch[0]), batch[1])


def linear_problem(n=200, seed=0):
    g = torch.Generator().manual_seed(seed)
    x = torch.randn(n, 5, generator=g)
    w = torch.tensor([[1.0], [-2.0], [0.5], [0.0], [3.0]])
    y = x @ w + 0.7 + 0.01 * torch.randn(n, 1, generator=g)
    return x, y


def config(**kw):
    base = dict(learning_rate=0.05, max_epochs=40, batch_size=32, grad_clip=None, patience=None)
    return TrainingConfig(**{**base, **kw})


def fresh_mlp(seed=0):
    torch.manual_seed(seed)
    return torch.nn.Sequential(torch.nn.Linear(5, 16), torch.nn.PReLU(), torch.nn.Linear(16, 1))


# --------------------------------------------------------------------------- fit_network
def test_fit_network_reduces_the_loss_of_a_learnable_problem():
    x, y = linear_problem()
    net = fresh_mlp()
    with torch.no_grad():
        initial = float(mse(net, (x[150:], y[150:])))
    hist = fit_network(net, (x[:150], y[:150]), (x[150:], y[150:]), mse, config())
    assert isinstance(hist, TrainingHistory)
    assert hist.n_epochs == 40 and len(hist.val_loss) == 40
    assert hist.train_loss[-1] < 0.01 * hist.train_loss[0]
    assert min(hist.val_loss) < 0.01 * initial
    assert not hist.stopped_early
    assert hist.seconds > 0


def test_early_stopping_restores_the_best_weights():
    # training pulls the weight from 0 to 1; the validation target 0.5 x is best half way
    x = torch.linspace(-1, 1, 64).reshape(-1, 1)
    net = torch.nn.Linear(1, 1, bias=False)
    with torch.no_grad():
        net.weight.zero_()
    cfg = config(learning_rate=0.02, max_epochs=500, batch_size=64, patience=5)
    hist = fit_network(net, (x, x), (x, 0.5 * x), mse, cfg)
    assert hist.stopped_early
    assert 0 < hist.best_epoch < hist.n_epochs - 1
    assert hist.n_epochs == hist.best_epoch + cfg.patience + 1
    assert hist.val_loss[-1] > hist.val_loss[hist.best_epoch]
    with torch.no_grad():
        restored = float(mse(net, (x, 0.5 * x)))
    assert restored == pytest.approx(hist.val_loss[hist.best_epoch], rel=1e-6)
    assert hist.best_loss == hist.val_loss[hist.best_epoch]
    assert float(net.weight.detach()) == pytest.approx(0.5, abs=0.05)


def test_without_validation_the_lowest_training_loss_is_kept():
    x, y = linear_problem()
    net = fresh_mlp()
    hist = fit_network(net, (x, y), None, mse, config(max_epochs=10))
    assert hist.val_loss == ()
    assert hist.best_epoch == int(np.argmin(hist.train_loss))


def _train_once(seed):
    x, y = linear_problem()
    net = fresh_mlp(seed=3)
    hist = fit_network(net, (x[:150], y[:150]), (x[150:], y[150:]), mse,
                       config(max_epochs=8, grad_clip=1.0), random_state=seed)
    return net, hist


def test_seeded_runs_are_bitwise_identical():
    (net1, h1), (net2, h2) = _train_once(7), _train_once(7)
    for p, q in zip(net1.parameters(), net2.parameters(), strict=True):
        assert torch.equal(p, q)
    assert h1.train_loss == h2.train_loss and h1.val_loss == h2.val_loss
    net3, h3 = _train_once(8)  # another seed: other shuffles
    assert h3.train_loss != h1.train_loss


def test_global_random_state_and_determinism_flag_are_restored():
    x, y = linear_problem()
    net = fresh_mlp()
    torch.manual_seed(99)
    np.random.seed(99)  # noqa: NPY002 - the legacy global state is what must be restored
    torch_state = torch.get_rng_state()
    np_state = np.random.get_state()  # noqa: NPY002
    flag = torch.are_deterministic_algorithms_enabled()
    fit_network(net, (x, y), (x, y), mse, config(max_epochs=2), random_state=5)
    assert torch.equal(torch.get_rng_state(), torch_state)
    assert np.array_equal(np.random.get_state()[1], np_state[1])  # noqa: NPY002
    assert torch.are_deterministic_algorithms_enabled() == flag


@pytest.mark.parametrize("clip", [1e-4, 0.5], ids=["paper-threshold", "0.5"])
def test_gradient_norm_is_clipped_before_every_step(monkeypatch, clip):
    norms: list[float] = []
    original = torch.optim.Adam.step

    def recording_step(self, *args, **kwargs):
        grads = [p.grad for g in self.param_groups for p in g["params"] if p.grad is not None]
        norms.append(float(torch.linalg.vector_norm(torch.stack([g.norm() for g in grads]))))
        return original(self, *args, **kwargs)

    monkeypatch.setattr(torch.optim.Adam, "step", recording_step)
    x, y = linear_problem()
    fit_network(fresh_mlp(), (x, 10 * y), None, mse, config(max_epochs=3, grad_clip=clip))
    assert len(norms) == 3 * math.ceil(200 / 32)
    assert max(norms) <= clip * (1 + 1e-5)
    norms.clear()
    fit_network(fresh_mlp(), (x, 10 * y), None, mse, config(max_epochs=1, grad_clip=None))
    assert max(norms) > 1.0  # without clipping the same problem has large gradients


def test_progress_bar_runs(capsys):
    x, y = linear_problem(n=40)
    hist = fit_network(fresh_mlp(), (x, y), (x, y), mse, config(max_epochs=2), progress=True)
    assert hist.n_epochs == 2
    assert "training" in capsys.readouterr().err


def test_non_finite_loss_stops_with_a_warning():
    x, y = linear_problem(n=40)
    net = fresh_mlp()

    def nan_loss(module, batch):
        return mse(module, batch) * float("nan")

    with pytest.warns(ConvergenceWarning, match="non-finite"):
        hist = fit_network(net, (x, y), None, nan_loss, config(max_epochs=3))
    assert hist.n_epochs == 0


@pytest.mark.parametrize(
    ("train", "val", "error", "match"),
    [
        ("not tensors", None, DataError, "tuple of tensors"),
        ((torch.zeros(4, 2), torch.zeros(3, 1)), None, DimensionError, "3 records"),
        ((torch.full((4, 5), float("nan")), torch.zeros(4, 1)), None, DataError, "NaN"),
        ((torch.zeros(4, 5), torch.zeros(4, 1)), (torch.zeros(2, 5), torch.zeros(3, 1)),
         DimensionError, "val"),
    ],
    ids=["not-tensors", "ragged-train", "nan-train", "ragged-val"],
)
def test_bad_data_raise(train, val, error, match):
    with pytest.raises(error, match=match):
        fit_network(fresh_mlp(), train, val, mse, config(max_epochs=1))


def test_config_must_be_a_training_config():
    x, y = linear_problem(n=10)
    with pytest.raises(DataError, match="TrainingConfig"):
        fit_network(fresh_mlp(), (x, y), None, mse, {"learning_rate": 0.1})


# --------------------------------------------------------------------------- presets
def test_paper_preset_values():
    cfg = TrainingConfig.preset("paper")
    assert cfg.learning_rate == 1e-5
    assert cfg.grad_clip == 1e-4  # MATLAB GradientThreshold on the global L2 norm
    assert cfg.max_epochs == 1000
    assert cfg.batch_size == 50
    assert cfg.patience is None  # MATLAB's ValidationPatience defaults to Inf
    assert cfg.weight_decay == 0.0
    assert cfg.validation_fraction == 0.15


def test_default_preset_is_valid_and_stops_early():
    cfg = TrainingConfig.preset("default")
    assert cfg.patience is not None and cfg.patience < cfg.max_epochs
    assert cfg.learning_rate > TrainingConfig.preset("paper").learning_rate
    assert cfg.validation_fraction == 0.15


def test_preset_overrides_and_round_trip():
    cfg = TrainingConfig.preset("default", max_epochs=7, patience=None)
    assert (cfg.max_epochs, cfg.patience) == (7, None)
    assert TrainingConfig.from_dict(cfg.to_dict()) == cfg


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [({"learning_rate": 0.0}, "learning_rate"), ({"max_epochs": 0}, "max_epochs"),
     ({"batch_size": 2.5}, "batch_size"), ({"grad_clip": -1.0}, "grad_clip"),
     ({"patience": 0}, "patience"), ({"weight_decay": -0.1}, "weight_decay"),
     ({"validation_fraction": 1.0}, "validation_fraction"), ({"momentum": 0.9}, "momentum")],
    ids=["lr", "epochs", "batch", "clip", "patience", "decay", "fraction", "unknown"],
)
def test_invalid_config_values_raise(kwargs, match):
    with pytest.raises(DataError, match=match):
        TrainingConfig.preset("default", **kwargs)


def test_unknown_preset_lists_the_valid_names():
    with pytest.raises(DataError, match="'default', 'paper'"):
        TrainingConfig.preset("fast")


def test_history_round_trips_through_a_dict():
    h = TrainingHistory([1.0, 0.5], [0.9, math.inf], best_epoch=0, seconds=1.5,
                        stopped_early=True)
    back = TrainingHistory.from_dict(h.to_dict())
    assert back.train_loss == h.train_loss and back.best_epoch == 0 and back.stopped_early
    assert math.isnan(back.val_loss[1])  # non-finite values are stored as null


# --------------------------------------------------------------------------- split and scaling
def test_split_indices_is_85_15_disjoint_and_seeded():
    train, val = split_indices(100, 0.15, random_state=4)
    assert (train.size, val.size) == (85, 15)
    np.testing.assert_array_equal(np.sort(np.concatenate([train, val])), np.arange(100))
    again = split_indices(100, 0.15, random_state=4)
    np.testing.assert_array_equal(again[1], val)
    assert not np.array_equal(split_indices(100, 0.15, random_state=5)[1], val)


def test_split_indices_keeps_one_validation_record():
    train, val = split_indices(3, 0.15)
    assert (train.size, val.size) == (2, 1)


@pytest.mark.parametrize(
    ("n", "fraction", "match"),
    [(1, 0.15, "n must be"), (10, 0.0, "validation_fraction"), (2, 0.9, "no training")],
    ids=["one-record", "zero-fraction", "all-validation"],
)
def test_split_indices_errors(n, fraction, match):
    with pytest.raises(DataError, match=match):
        split_indices(n, fraction)


def test_standardizer_round_trip_and_constant_feature():
    rng = np.random.default_rng(0)
    x = np.column_stack([rng.normal(3.0, 2.0, 50), np.full(50, 7.0)])
    s = Standardizer.fit(x)
    z = s.transform(x)
    np.testing.assert_allclose(z[:, 0].mean(), 0.0, atol=1e-12)
    np.testing.assert_allclose(z[:, 0].std(), 1.0, rtol=1e-12)
    assert s.scale[1] == 1.0  # a constant feature is only shifted
    np.testing.assert_allclose(s.inverse_transform(z), x, rtol=1e-14, atol=1e-14)
    back = Standardizer.from_dict(s.to_dict())
    np.testing.assert_array_equal(back.mean, s.mean)
    np.testing.assert_array_equal(back.scale, s.scale)


def test_standardizer_errors():
    with pytest.raises(DataError, match="NaN"):
        Standardizer.fit([[1.0], [np.nan]])
    with pytest.raises(DimensionError, match="n_records"):
        Standardizer.fit([1.0, 2.0])
    with pytest.raises(DimensionError, match="3 features"):
        Standardizer.fit(np.ones((4, 2))).transform(np.ones((1, 3)))
    with pytest.raises(DataError, match="positive"):
        Standardizer([0.0], [0.0])
    with pytest.raises(DataError, match="standardizer"):
        Standardizer.from_dict({"mean": [0.0]})


def test_no_warnings_in_a_normal_run():
    x, y = linear_problem(n=40)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        fit_network(fresh_mlp(), (x, y), (x, y), mse, config(max_epochs=2, grad_clip=1.0))


def test_standardizer_constant_scale_for_labels():
    # labels of a system without uncertainty are constant: with a negligible scale, whatever
    # a network outputs maps back to the constant (the -148 % paper_dnn fit at 0 % uncertainty)
    s = Standardizer.fit(np.full((5, 2), 0.3), constant_scale=None)
    # the scale is the detection threshold 1e-12 * 0.3: an output of 2 moves the label by 6e-13
    np.testing.assert_allclose(s.inverse_transform(np.array([[2.0, -1.0]])), [[0.3, 0.3]],
                               rtol=1e-11)
