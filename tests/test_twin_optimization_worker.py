"""The MPC weight retuning in a child process (twin/optimization/background.py, kind='process')."""

from __future__ import annotations

from concurrent.futures import Future
from dataclasses import replace

import numpy as np
import pytest

from kautztwin.twin.optimization import Optimizer
from kautztwin.twin.optimization import background as bg
from kautztwin.twin.runtime import DigitalTwin, TwinConfig, make_plant


def _tuning_args():
    """The arguments of one real retuning: the first version of a quick hydraulic twin."""
    plant = make_plant("hydraulic", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=20.0, quick=True, static_twin=False)
    with DigitalTwin(plant, cfg) as twin:
        twin.start()
        while twin.updater is None:
            twin.step()
        model = twin.updater.digital_model.model
        v = np.full(twin.k, cfg.operating_input)
    return (Optimizer(), model, cfg.mpc, 3.0, cfg.operating_input, 98.0, cfg.mpc, None,
            v, np.zeros_like(v), 0.0, None)


def _same_tuning(a, b):
    assert a.tuning.accepted == b.tuning.accepted and a.tuning.settings == b.tuning.settings
    assert [(c.r, c.score, c.valid) for c in a.tuning.candidates] == [
        (c.r, c.score, c.valid) for c in b.tuning.candidates]
    assert len(a.prepared) == len(b.prepared)
    for (ma, sa, pa), (mb, sb, pb) in zip(a.prepared, b.prepared, strict=True):
        assert ma is mb and sa == sb
        np.testing.assert_array_equal(pa.xv, pb.xv)  # built the same way, in this thread
        np.testing.assert_array_equal(pa.xd, pb.xd)


class _BrokenChild:
    """An executor whose child has died: every job fails (BrokenProcessPool in real life)."""

    def submit(self, fn, *args, **kwargs):
        fut: Future = Future()
        fut.set_exception(RuntimeError("A child process terminated abruptly"))
        return fut


def test_the_child_process_returns_the_thread_s_tuning_and_a_broken_child_is_not_fatal(caplog):
    args = _tuning_args()
    here = bg._tune_in_worker(*args)
    worker = bg.OptimizationWorker(Optimizer(), event=None, install=None, apply_tuning=None,
                                   apply_retraining=None, context=None, kind="process")
    try:
        worker.prestart()
        child = worker._child()
        assert child is worker._child()  # one child, started once
        # the child itself computes it (models and settings cross the process boundary)
        alone = child.submit(bg._tune, *args[:6]).result(timeout=120)
        with caplog.at_level("WARNING", logger=bg.__name__):
            remote = bg._tune_in_worker(*args, child)
        assert not caplog.records  # no fallback to the thread
    finally:
        worker.close()
    assert worker._process is None  # closed with the worker
    assert alone.settings == here.tuning.settings
    assert [c.score for c in alone.candidates] == [c.score for c in here.tuning.candidates]
    _same_tuning(remote, here)
    with caplog.at_level("WARNING", logger=bg.__name__):
        broken = bg._tune_in_worker(*args, _BrokenChild())
    assert "failed in the child process" in caplog.text
    _same_tuning(broken, here)  # tuned in the thread instead
    assert here.tuning.candidates  # a real tuning, not an empty one
    with pytest.raises(ValueError, match="'thread' or 'process'"):
        bg.OptimizationWorker(Optimizer(), event=None, install=None, apply_tuning=None,
                              apply_retraining=None, context=None, kind="fork")


def test_a_background_twin_with_a_process_worker_tunes_in_its_child():
    plant = make_plant("hydraulic", drift=0.4, drift_events=(12.0,), seed=0)
    cfg = TwinConfig.for_plant(plant, duration=24.0, quick=True, static_twin=False)
    cfg = replace(cfg, updater={**cfg.updater, "worker": "process"})
    with DigitalTwin(plant, cfg, background=True) as twin:
        twin.start()
        worker = twin._versions.worker
        assert worker.kind == "process" and worker._process is not None  # prestarted
        while twin.updater is None:  # to the closed loop: the first version is tuned here
            state = twin.step()
        assert "controller" in state.events and not twin.optimizing
        twin.step()
        dm = twin.updater.snapshot("rls-consolidation")  # a new version: tuned in the child
        assert "model-version" in twin.step().events
        assert twin.optimizing and twin.wait_optimization(120)
        state = twin.step()  # applies it
        assert "controller" in state.events
        run = twin.run(progress=False)
        tunings = [e for e in run.events if e.kind == "controller"]
    assert worker._process is None  # the child is stopped with the twin
    assert run.status == "finished" and "k_submitted" not in tunings[0].payload
    assert tunings[1].payload["version"] == dm.version
    assert all(e.payload["k_submitted"] < e.k for e in tunings[1:])  # applied when done
    assert all("normalised IAE" in e.payload["reason"] for e in tunings)


def test_process_workers_start_before_the_plant_is_reset():
    """The first worker process waits for the forkserver to import the library (about 1 s).

    Started after the plant's reset, that stalled a live plant's identification while its
    samples flowed (against the OPC UA plant at x10, 24 to 38 switches of the excitation
    reached the plant instead of 68, and the first closed-loop windows scored 92 to
    94 %): the workers start first.
    """
    plant = make_plant("hydraulic", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=24.0, quick=True, static_twin=False)
    cfg = replace(cfg, updater={**cfg.updater, "worker": "process"})
    seen: dict[str, bool] = {}

    class _Watched:
        """The plant; its reset records which of the twin's workers already run."""

        def __getattr__(self, name):
            return getattr(plant, name)

        def reset(self):
            seen["tuning"] = twin._versions.worker._process is not None
            seen["poles"] = twin._versions.poles is not None
            return plant.reset()

    with DigitalTwin(_Watched(), cfg, background=True) as twin:
        twin.start()
    assert seen == {"tuning": True, "poles": True}
