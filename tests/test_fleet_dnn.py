"""The fleet's update module with a neural estimator, and its memory savings (issue #15).

* The DNN fast path: the due assets' virtual step tests go to the estimator in
  ONE ``predict_models`` call (counted), and each candidate equals the one the
  estimator gives for that asset's record alone (oracle: the step response of
  the asset's live model simulated by :func:`scipy.signal.dlsim`, then one
  estimator call per asset).
* The update module's buffer takes its inputs from the fleet's command history:
  they are exactly the inputs the plants got (the recorded ``u``).
* The limit violations counted during a run equal those :func:`summarize`
  computes from the records.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
import torch
from scipy import signal

import kautztwin as kt
from kautztwin.datasets import paper_system
from kautztwin.exceptions import DataError
from kautztwin.nn.adaptive import AdaptivePoleEstimator
from kautztwin.nn.adaptive.inference import predict_params
from kautztwin.twin.fleet import Fleet
from kautztwin.twin.fleet.simulate import hydraulic_fleet, summarize
from kautztwin.twin.runtime import TwinConfig

torch.set_num_threads(1)


class CountingEstimator:
    """An estimator that counts its ``predict_models`` calls and keeps what they returned."""

    def __init__(self, est: AdaptivePoleEstimator) -> None:
        self.est = est
        self.t_, self.kind_, self.n_functions_ = est.t_, est.kind_, est.n_functions_
        self.calls: list[tuple[np.ndarray, list]] = []

    def predict_models(self, records, *, t=None):
        models = self.est.predict_models(records, t=t)
        self.calls.append((np.array(records), models))
        return models


@pytest.fixture(scope="module")
def estimator() -> AdaptivePoleEstimator:
    # a small network on step responses of the twins' grid (dt = 0.02 s): 3 basis functions,
    # the twins' models without their extra fast-path pole
    t = 0.02 * np.arange(150)
    est = AdaptivePoleEstimator(hidden=(8,), n_features=8, n_stages=1, pretrain_epochs=0,
                                structure=("real", "pair"), config={"max_epochs": 1},
                                random_state=0)
    return est.fit_distribution(paper_system(), 0.3, t, noise=0.01, n_train=300, kind="step")


@pytest.fixture(scope="module")
def fleet(estimator):
    cfg = TwinConfig.for_plant("hydraulic", duration=8.0, quick=True, static_twin=False,
                               retune=False)
    plant, _ = hydraulic_fleet(3, cfg, seed=5, drift_spread=0.0)
    f = Fleet(plant, cfg, estimator=CountingEstimator(estimator))
    f.run(until=cfg.n_ident + 80, progress=False)
    return f


def test_inputs_come_from_the_command_history_exactly(fleet) -> None:
    upd = fleet.updater
    assert upd.buf_u is None  # the buffer keeps outputs only
    k = fleet.k
    for i in range(fleet.n_assets):
        np.testing.assert_array_equal(fleet._inputs(i, 0, k), fleet.arrays["u"][i, :k])
        u, _ = upd.buffer(i)
        np.testing.assert_array_equal(u, fleet.arrays["u"][i, k - u.size:k])


def test_dnn_candidates_batched_equal_per_asset_estimates(fleet, estimator) -> None:
    upd = fleet.updater
    counting = upd.estimator
    n = upd.n
    grid = np.rint(estimator.t_ / fleet.config.dt).astype(int)
    # oracle records: each live model's unit step response, simulated independently
    oracle = []
    for i in range(fleet.n_assets):
        live = kt.KautzModel(upd.wide_basis[i], upd.theta[i, :n].copy())
        A, B, C, D = live.state_space()
        _, y, _ = signal.dlsim((A, B, C, D, fleet.config.dt), np.ones(grid.max() + 1))
        oracle.append(y[grid, 0])
    before = len(counting.calls)
    outcomes = upd.dnn_update(np.arange(fleet.n_assets))
    assert len(counting.calls) == before + 1  # one call for the three assets
    records, models = counting.calls[-1]
    assert records.shape == (3, grid.size)
    np.testing.assert_allclose(records, np.array(oracle), rtol=1e-12,
                               atol=1e-12 * np.abs(oracle).max())
    for i in range(3):  # the batch gives each record what a call on it alone gives
        alone = estimator.predict_models(records[i], t=estimator.t_)[0]
        np.testing.assert_allclose(models[i].poles, alone.poles, rtol=1e-12, atol=0)
        # how closely can they agree?  The estimator's own arithmetic depends on the batch:
        # its basis signals K (step responses A^-1 (e^At - I) B, matrix exponentials of the
        # whole batch) differ between a batched and a single evaluation by basis_err, and
        # its least squares (normal equations) rounds to eps * cond(K)^2
        t = estimator.t_
        net = estimator.network_
        params = predict_params(net, records)
        np.testing.assert_array_equal(params[i:i + 1], predict_params(net, records[i:i + 1]))
        K_b = net.design(torch.as_tensor(params)).numpy()[i]
        K_1 = net.design(torch.as_tensor(params[i:i + 1])).numpy()[0]
        basis_err = np.abs(K_b - K_1).max() / np.abs(K_1).max()
        bound = 10 * (basis_err + np.finfo(float).eps * np.linalg.cond(K_1) ** 2)
        assert bound < 1e-6, bound  # a meaningful bound
        y_b, y_1 = models[i].step(t), alone.step(t)
        np.testing.assert_allclose(y_b, y_1, rtol=0, atol=bound * np.abs(y_1).max())
        np.testing.assert_allclose(models[i].coefficients, alone.coefficients, rtol=bound,
                                   atol=0)
    assert [o.asset for o in outcomes] == [0, 1, 2]
    for o in outcomes:
        dm = upd.digital_models[o.asset]
        if o.accepted:
            assert dm.provenance == "dnn-update" and dm.version == o.version
            disc = np.exp(np.sort_complex(models[o.asset].poles) * fleet.config.dt)
            np.testing.assert_allclose(np.sort_complex(dm.model.poles), np.sort_complex(disc),
                                       rtol=1e-12)
        else:
            assert dm.version == o.version


def test_due_attempts_of_a_sample_make_one_estimator_call(fleet) -> None:
    upd = fleet.updater
    counting = upd.estimator
    attempts = upd.counts["attempts"].copy()
    upd.rec_on[:] = True  # every asset due at the next sample
    upd.rec_next[:] = upd.k + 1
    upd.rec_attempts[:] = 0
    before = len(counting.calls)
    fleet.step()
    assert len(counting.calls) == before + 1
    assert counting.calls[-1][0].shape[0] == 3
    np.testing.assert_array_equal(upd.counts["attempts"], attempts + 1)


def test_estimator_must_fit_the_twins(estimator) -> None:
    from kautztwin.twin.fleet.update import FleetUpdater

    assert FleetUpdater._check_estimator(_Stub(), estimator).tolist() == list(range(150))
    odd = CountingEstimator(estimator)
    odd.t_ = estimator.t_ + 0.005  # not on the twins' samples

    with pytest.raises(DataError, match="samples of the twin's dt"):
        FleetUpdater._check_estimator(_Stub(), odd)
    impulse = CountingEstimator(estimator)
    impulse.kind_ = "impulse"
    with pytest.raises(DataError, match="step responses"):
        FleetUpdater._check_estimator(_Stub(), impulse)
    wide = CountingEstimator(estimator)
    wide.n_functions_ = 4
    with pytest.raises(DataError, match="4 basis functions"):
        FleetUpdater._check_estimator(_Stub(), wide)


class _Stub:
    dt, n = 0.02, 4
    extra_poles = [np.array([-1.0])]


def test_violations_counted_in_the_run_equal_the_records() -> None:
    cfg = TwinConfig.for_plant("hydraulic", duration=8.0, quick=True, static_twin=False,
                               retune=False)
    assert cfg.mpc is not None
    # an output limit just above the one set-point: the sensor noise (0.01) crosses it
    cfg = replace(cfg, setpoints=((3.2, 100.0),), mpc=replace(cfg.mpc, y_max=100.015))
    plant, assets = hydraulic_fleet(2, cfg, seed=6, drift_spread=0.0)
    run = Fleet(plant, cfg).run(progress=False)
    from_records = summarize(run)["violations"]
    no_records = replace(run, arrays={})
    assert summarize(no_records)["violations"] == from_records
    assert from_records["output_samples"] > 0


def test_cli_fleet_run_with_an_estimator(estimator, tmp_path, capsys) -> None:
    import json

    from kautztwin.cli.main import main

    folder = tmp_path / "est"
    estimator.save(folder)
    (folder / "estimator.json").write_text(json.dumps({"estimator": "adaptive"}))
    out = tmp_path / "run"
    assert main(["fleet", "run", "--assets", "2", "--duration", "6", "--estimator",
                 str(folder), "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["n_assets"] == 2
    capsys.readouterr()
    assert main(["fleet", "run", "--assets", "2", "--estimator", str(tmp_path / "none"),
                 "--out", str(out)]) == 2
    assert "no estimator folder" in capsys.readouterr().err
    assert main(["fleet", "run", "--assets", "2", "--shards", "2", "--estimator", str(folder),
                 "--out", str(out)]) == 2
    assert "--estimator runs in one process" in capsys.readouterr().err
