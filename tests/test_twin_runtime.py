"""Twin runtime: DigitalTwin loop, MPC tracking, faults, optimizer, report, resume after kill -9."""

from __future__ import annotations

import json
import math
import os
import signal
import sqlite3
import subprocess
import sys
import textwrap
import threading
import time
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

import kautztwin as kt
from kautztwin.exceptions import DataError
from kautztwin.twin import Clock, HydraulicPlant, SampleFlag, SQLiteHistory, run_open_loop
from kautztwin.twin import runtime as runtime_module
from kautztwin.twin.optimization import ControllerTuning, Optimizer
from kautztwin.twin.prediction import MPCSettings, build_mpc
from kautztwin.twin.prediction import controller as controller_module
from kautztwin.twin.report import compute_metrics, rolling_fit, write_report
from kautztwin.twin.runtime import (
    DigitalTwin,
    FaultConfig,
    MPCController,
    TwinConfig,
    TwinError,
    TwinState,
    make_plant,
    parse_setpoints,
)

REPO = Path(__file__).resolve().parent.parent
METRIC_KEYS = (
    "sync_fit_mean", "sync_fit_min_after_recovery", "static_twin_sync_fit_mean",
    "reidentifications", "tracking_iae", "constraint_violations", "mpc_solve_ms", "update_ms",
)
FAULTS = "dropout=0.02,outlier=0.01,late=0.01"


# --------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def hydraulic_run(tmp_path_factory):
    """A short hydraulic run: 40 % pole drift at 12 s and 20 s, sensor faults, SQLite store."""
    store = tmp_path_factory.mktemp("hyd") / "history.sqlite"
    plant = make_plant("hydraulic", drift=0.4, drift_events=(12.0, 20.0), seed=0)
    cfg = TwinConfig.for_plant(plant, duration=28.0, quick=True, faults=FAULTS, setpoints="97,102")
    twin = DigitalTwin(plant, cfg, history=store)
    run = twin.run(progress=False)
    what_if = twin.what_if(np.full(50, run.arrays["u"][-1] + 0.05))  # open the valve more
    twin.close()
    return run, compute_metrics(run), store, what_if


@pytest.fixture(scope="module")
def tclab_run():
    """A short TCLab (emulator) run with set-point steps."""
    plant = make_plant("tclab", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=1500.0, quick=True, setpoints="50,42")
    twin = DigitalTwin(plant, cfg)
    run = twin.run(progress=False)
    twin.close()
    return run, compute_metrics(run)


# --------------------------------------------------------------------------- the loop
@pytest.mark.parametrize("fixture", ["hydraulic_run", "tclab_run"], ids=["hydraulic", "tclab"])
def test_mpc_tracks_setpoint_steps_without_violating_constraints(fixture, request):
    run, m = request.getfixturevalue(fixture)[:2]
    assert run.status == "finished" and run.n_done == run.config.n_samples
    assert m["constraint_violations"] == 0 and m["max_violation"] == 0.0
    assert m["mpc_failures"] == 0
    # every set-point is reached: the mean over the second half of each segment is close
    span = run.config.mpc.y_max - max(run.config.mpc.y_min, 0.0)
    assert m["settled_error_max"] < 0.02 * span
    a = run.arrays
    cl = slice(run.k_closed_loop, None)
    mpc = run.config.mpc
    assert np.all((a["u"][cl] >= mpc.u_min) & (a["u"][cl] <= mpc.u_max))
    assert np.max(np.abs(np.diff(a["u"][cl]))) <= mpc.du_max + 1e-12
    assert m["mpc_solve_ms"]["median"] < 1.0 and m["update_ms"]["median"] < 5.0


def test_every_metric_of_the_issue_is_reported(hydraulic_run):
    _, m, _, _ = hydraulic_run
    for key in METRIC_KEYS:
        assert key in m, key
    assert set(m["mpc_solve_ms"]) >= {"median", "p99"} and set(m["update_ms"]) >= {"median", "p99"}
    assert m["drift_events_s"] == [12.0, 20.0] and m["recovery_window_s"] == 15.0
    json.dumps(m, allow_nan=False)  # strict JSON


def test_updating_twin_beats_the_static_twin_after_a_drift(hydraulic_run):
    run, m, _, _ = hydraulic_run
    # synchronised before the drift (the first windows hold the switch to closed loop and faults)
    assert m["sync_fit_min_before_drift"] >= 90.0
    assert m["sync_fit_mean"] > m["static_twin_sync_fit_mean"] + 20.0
    assert m["static_twin_sync_fit_mean_after_drift"] < 80.0
    kinds = {e.kind for e in run.events}
    assert {"drift", "desync", "model-version", "controller"} <= kinds
    assert m["model_version"] == run.versions[-1]["version"]
    assert m["reidentification_attempts"] > 0


def test_sensor_faults_are_flagged_counted_and_skipped(hydraulic_run):
    run, m, store, _ = hydraulic_run
    s = m["samples"]
    assert s["dropouts"] > 0 and s["outliers"] > 0 and s["late"] > 0
    assert s["skipped"] >= s["dropouts"] + s["late"]
    a = run.arrays
    flags = a["flags"]
    assert np.all(np.isfinite(a["u"]))  # never a NaN input to the plant
    assert np.isnan(a["y"][(flags & SampleFlag.DROPOUT) > 0]).all()
    assert np.isnan(a["y_clean"][(flags & (SampleFlag.OUTLIER | SampleFlag.HELD)) > 0]).all()
    with SQLiteHistory(store) as h:
        stored = h.measurements(run.run_id)
    np.testing.assert_array_equal(stored.flags, flags)
    assert int(np.sum((stored.flags & SampleFlag.LATE) > 0)) == s["late"]


def test_history_holds_every_sample_and_model_version(hydraulic_run):
    run, _, store, _ = hydraulic_run
    with SQLiteHistory(store) as h:
        info = h.run_info(run.run_id)
        rows = h.measurements(run.run_id)
        versions = [v.version for v in h.model_versions(run.run_id)]
        active = h.active_model(run.run_id)
    assert info.status == "finished"
    np.testing.assert_array_equal(rows.k, np.arange(run.n_done))
    np.testing.assert_array_equal(rows.u, run.arrays["u"])
    assert versions == [v["version"] for v in run.versions]
    assert active.version == versions[-1]


def test_what_if_predicts_a_planned_input(hydraulic_run):
    *_, y = hydraulic_run
    assert y.shape == (50,) and np.all(np.isfinite(y))
    assert y[-1] > y[0]  # more valve, more speed


def test_step_returns_immutable_states_and_errors_are_clear():
    plant = HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1)
    cfg = TwinConfig.for_plant(plant, duration=5.0, quick=True, static_twin=False)
    twin = DigitalTwin(plant, cfg)
    with pytest.raises(TwinError, match="start"):
        twin.step()
    with pytest.raises(TwinError, match="no model yet"):
        twin.what_if([0.5])
    state = twin.start()
    assert isinstance(state, TwinState) and state.k == -1
    s0 = twin.step()
    with pytest.raises(AttributeError):
        s0.k = 5  # frozen
    states = [twin.step() for _ in range(cfg.n_ident + 5)]
    assert states[0].phase == "identification" and states[-1].phase == "closed-loop"
    assert states[-1].version >= 1 and math.isfinite(states[-1].command)
    with pytest.raises(DataError, match="dt"):
        DigitalTwin(plant, TwinConfig.for_plant("tclab", quick=True))


# --------------------------------------------------------------------------- resume
def _config(duration=10.0):
    plant = make_plant("hydraulic", seed=0)
    return plant, TwinConfig.for_plant(plant, duration=duration, quick=True, faults=FAULTS)


def test_resume_after_an_interruption_replays_to_the_identical_run(tmp_path):
    store = tmp_path / "h.sqlite"
    plant, cfg = _config()
    twin = DigitalTwin(plant, cfg, history=store)
    twin.start()
    for _ in range(333):  # mid closed loop, mid commit batch
        twin.step()
    twin.finish()  # commits what is pending; the run stays resumable
    twin.close()
    plant2, cfg2 = _config()
    resumed = DigitalTwin(plant2, cfg2, history=store).run(progress=False)
    assert resumed.resume["resumed"] and resumed.resume["resume_k"] == 333
    assert resumed.resume["replay_mismatches"] == 0 and resumed.run_id == 1
    plant3, cfg3 = _config()
    straight = DigitalTwin(plant3, cfg3).run(progress=False)
    for name in ("u", "y", "y_pred", "version"):
        np.testing.assert_array_equal(resumed.arrays[name], straight.arrays[name], err_msg=name)
    with SQLiteHistory(store) as h:
        rows = h.measurements(1)
        assert [r.status for r in h.runs()] == ["finished"]
        assert sum(e.kind == "resume" for e in h.events(1)) == 1
    np.testing.assert_array_equal(rows.k, np.arange(cfg.n_samples))


_KILL_SCRIPT = textwrap.dedent("""
    import sys
    from kautztwin.twin import Clock
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig, make_plant
    plant = make_plant("hydraulic", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=10.0, quick=True, faults="{faults}",
                               commit_every=20)
    speedup = float(sys.argv[2])
    clock = Clock.real_time(speedup) if speedup > 0 else None
    # compared sample by sample with an uninterrupted run: synchronous re-identification
    twin = DigitalTwin(plant, cfg, history=sys.argv[1], clock=clock, background=False)
    run = twin.run(progress=False)
    print(run.status, run.resume["resume_k"], run.resume["replay_mismatches"])
""").format(faults=FAULTS)


def _rows(path: Path) -> list[tuple]:
    con = sqlite3.connect(f"file:{path}?mode=ro", uri=True, timeout=5)
    try:
        return con.execute("SELECT k, t, u, y, flags FROM measurements ORDER BY k").fetchall()
    except sqlite3.OperationalError:  # schema not created yet
        return []
    finally:
        con.close()


def test_kill_9_mid_run_resumes_without_losing_a_committed_sample(tmp_path):
    store = tmp_path / "history.sqlite"
    script = tmp_path / "twin_script.py"
    script.write_text(_KILL_SCRIPT)
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "PYTHONPATH": str(REPO / "src")}
    proc = subprocess.Popen([sys.executable, str(script), str(store), "2"], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    deadline = time.monotonic() + 60
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            if store.exists() and len(_rows(store)) >= 300:
                break
            time.sleep(0.05)
        assert proc.poll() is None, proc.communicate()
        proc.send_signal(signal.SIGKILL)
        proc.wait(10)
    finally:
        if proc.poll() is None:  # pragma: no cover - only when the test fails
            proc.kill()
    assert proc.returncode == -signal.SIGKILL
    before = _rows(store)
    n = len(before)
    assert 300 <= n < 500 and [r[0] for r in before] == list(range(n))
    out = subprocess.run([sys.executable, str(script), str(store), "0"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    status, resume_k, mismatches = out.stdout.split()
    assert (status, int(resume_k), int(mismatches)) == ("finished", n, 0)
    after = _rows(store)
    assert [r[0] for r in after] == list(range(500))
    assert after[:n] == before  # every committed sample is kept, unchanged
    plant, cfg = _config()
    straight = DigitalTwin(plant, replace(cfg, commit_every=20)).run(progress=False)
    np.testing.assert_array_equal([r[2] for r in after], straight.arrays["u"])


# --------------------------------------------------------------------------- background
def _reid_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("kautztwin-reidentify")]


def test_background_reidentification_defaults_to_the_real_time_clock():
    plant, cfg = _config()
    cases = [
        ({}, cfg, False),  # as fast as possible: synchronous, reproducible
        ({"clock": Clock.real_time(10.0)}, cfg, True),
        ({"clock": Clock.real_time(10.0), "background": False}, cfg, False),
        ({}, replace(cfg, updater={**cfg.updater, "background": True}), True),
        ({"background": False}, replace(cfg, updater={**cfg.updater, "background": True}), False),
    ]
    for kwargs, config, expected in cases:
        with DigitalTwin(plant, config, **kwargs) as twin:
            assert twin.background is expected, kwargs
    with pytest.raises(DataError, match="background must be True, False or None"):
        DigitalTwin(plant, cfg, background="on")


def test_background_run_judges_attempts_later_and_close_joins_the_worker():
    plant = make_plant("hydraulic", drift=0.4, drift_events=(10.0,), seed=0)
    cfg = TwinConfig.for_plant(plant, duration=22.0, quick=True, static_twin=False)
    with DigitalTwin(plant, cfg, background=True) as twin:
        twin.start()
        while twin.updater is None or not twin.updater.pending:  # the drift starts a recovery
            twin.step()
        upd = twin.updater
        k_submitted = upd.k
        assert upd.background and upd.wait(30)
        state = twin.step()  # judges the finished attempt and logs it
        assert {"model-update", "model-rejected"} & set(state.events)
        assert (upd.model_updates[-1].k_submitted, upd.model_updates[-1].k) == (
            k_submitted, k_submitted + 1)
        run = twin.run(progress=False)  # the rest, with further attempts in the background
        assert run.status == "finished"
        fitted = [m for m in upd.model_updates
                  if m.kind == "reidentification" and "too few samples" not in m.reason]
        assert all(m.k > m.k_submitted for m in fitted)  # judged after they were submitted
        assert upd.counts["attempts"] == len(upd.model_updates) + upd.pending
        assert run.counts["reidentification_attempts"] == upd.counts["attempts"]
    assert not upd.pending and not _reid_threads()


def test_a_controller_that_cannot_be_built_for_a_new_version_is_kept(monkeypatch):
    # a validated model version can still give a QP the solver refuses (seen with DAQP: "setup
    # failed (exit flag -1)" on a nearly input-independent first output row); the loop goes on
    plant, cfg = _config()
    with DigitalTwin(plant, cfg) as twin:
        twin.start()
        while twin.k <= twin.config.n_ident:
            twin.step()
        running = twin.controller.problem

        def refuse(model, settings, **kwargs):
            raise DataError("DAQP setup failed (exit flag -1)")

        monkeypatch.setattr(controller_module, "build_mpc", refuse)
        dm = twin.updater.snapshot("rls-consolidation")  # a new version for the controller
        state = twin.step()
        assert state.version == dm.version and "controller-rejected" in state.events
        assert twin.controller.problem is running
        assert "cannot be set up" in twin.result().events[-1].message
        for _ in range(20):
            assert math.isfinite(twin.step().command)


def test_cli_background_flag_reaches_the_twin(capsys, tmp_path, monkeypatch):
    from kautztwin.cli.main import main

    seen = []

    class Spy(DigitalTwin):
        def run(self, *args, **kwargs):
            seen.append(self.background)
            raise TwinError("stopped by the test")

    monkeypatch.setattr(runtime_module, "DigitalTwin", Spy)
    base = ["twin", "run", "--plant", "hydraulic", "--quick", "--no-progress"]
    for extra, expected in [([], False), (["--speedup", "50"], True),
                            (["--speedup", "50", "--no-background"], False),
                            (["--background"], True)]:
        code = main([*base, *extra, "--out", str(tmp_path / f"o{len(seen)}")])
        assert code == 2 and "stopped by the test" in capsys.readouterr().err
        assert seen[-1] is expected, extra


# ------------------------------------------------------------------ background optimization
def _opt_threads() -> list[threading.Thread]:
    return [t for t in threading.enumerate() if t.name.startswith("kautztwin-optimize")]


def _quiet_config():
    """The quick hydraulic profile without re-identification: versions come only from the test."""
    plant = make_plant("hydraulic", seed=0)
    cfg = TwinConfig.for_plant(plant, duration=10.0, quick=True, static_twin=False)
    return plant, replace(cfg, updater={**cfg.updater, "reidentify": False})


class _ScriptedOptimizer(Optimizer):
    """Scripted weight tunings: the first keeps the weights, later ones multiply r by 5.

    With ``hold``, every tuning after the first waits in the worker for ``release``;
    with ``accept=False`` the later ones are rejected.
    """

    def __init__(self, *, hold=False, accept=True):
        super().__init__()
        self.hold, self.accept = hold, accept
        self.entered, self.release = threading.Event(), threading.Event()
        self.models = []
        self.threads = []

    def tune_controller(self, model, settings, *, step, u_op=None, y_op=0.0):
        n = len(self.models)
        self.models.append(model)
        self.threads.append(threading.current_thread().name)
        if n and self.hold:
            self.entered.set()
            if not self.release.wait(30):  # pragma: no cover - only when the test fails
                raise TwinError("the test never released the tuning")
        if n and not self.accept:
            return ControllerTuning(False, settings, reason=f"scripted rejection {n}")
        new = settings if n == 0 else settings.with_weight(5 * settings.r)
        return ControllerTuning(True, new, reason=f"scripted tuning {n}")


def _to_closed_loop(twin):
    """Start and run through the identification and the first closed-loop sample.

    The first version's controller is tuned at the end of the identification, before
    the first closed-loop sample, in background runs too (no worker involved).
    """
    twin.start()
    while twin.k < twin.config.n_ident:
        twin.step()
    state = twin.step()  # the identification, the first tuning and the first command
    assert "controller" in state.events and not twin.optimizing
    twin.step()


def _step_until(twin, kind, n=100):
    for _ in range(n):
        assert twin.wait_optimization(30)
        state = twin.step()
        if kind in state.events:
            return state
    raise AssertionError(f"no {kind!r} event in {n} samples")  # pragma: no cover


def _last(twin, prefix):
    return [e for e in twin.result().events if e.kind.startswith(prefix)][-1]


def _same_state(ctl, reference):
    f, ref = ctl._filter, reference._filter
    for name in ("xv", "xv_prev", "xd", "x0"):
        np.testing.assert_array_equal(getattr(f, name), getattr(ref, name), err_msg=name)
    assert f.nb == ref.nb
    np.testing.assert_array_equal(f.buf[:f.nb], ref.buf[:ref.nb])


def _rebuilt(twin, model, settings):
    """A controller rebuilt on the whole history (what the synchronous path would run)."""
    a = twin.result().arrays
    ref = MPCController(input_offset=twin.config.operating_input)
    ref.rebuild(model, settings, a["command"], a["dither"])
    return ref


def test_background_retuning_runs_off_the_sampling_path_and_is_applied_later():
    twins = {}
    for background in (False, True):
        plant, cfg = _quiet_config()
        twins[background] = DigitalTwin(plant, cfg, optimizer=_ScriptedOptimizer(hold=background),
                                        background=background)
    sync, twin = twins[False], twins[True]
    opt, mpc = twin.optimizer, twin.config.mpc
    try:
        for tw in (sync, twin):
            _to_closed_loop(tw)
        # the first version's tuning ran before the closed loop, in the sampling thread
        assert opt.threads == ["MainThread"] and not _opt_threads()
        np.testing.assert_array_equal(twin.result().arrays["u"], sync.result().arrays["u"])
        dm_sync = sync.updater.snapshot("rls-consolidation")
        dm = twin.updater.snapshot("rls-consolidation")
        k_new = twin.k
        assert "controller" in sync.step().events
        state = twin.step()  # submits the retuning and returns while the worker holds it
        assert "model-version" in state.events and "controller" not in state.events
        assert opt.entered.wait(30) and twin.optimizing
        for _ in range(10):  # the loop goes on: the new model with the running weights
            state = twin.step()
            assert math.isfinite(state.command) and state.version == dm.version
        assert twin.controller.model is dm.model and twin.controller.settings == mpc
        _same_state(twin.controller, _rebuilt(twin, dm.model, mpc))
        opt.release.set()
        state = _step_until(twin, "controller")
        assert not twin.optimizing
        ev_sync, ev = _last(sync, "controller"), _last(twin, "controller")
        assert (ev.kind, ev.message) == (ev_sync.kind, ev_sync.message) == (
            "controller", f"MPC rebuilt on version {dm.version}: scripted tuning 1")
        assert (ev.k, ev.payload["k_submitted"]) == (state.k, k_new) and state.k > k_new + 10
        rec_sync, rec = sync.result().tunings[-1], twin.result().tunings[-1]
        assert {key: rec[key] for key in rec_sync if key not in ("k", "t")} == {
            key: val for key, val in rec_sync.items() if key not in ("k", "t")}
        assert rec["r"] == 5 * mpc.r and rec["version"] == dm_sync.version == dm.version
        assert twin.controller.model is dm.model
        assert twin.controller.settings == sync.controller.settings != mpc
        _same_state(twin.controller, _rebuilt(twin, dm.model, twin.controller.settings))
        assert math.isfinite(twin.step().command)
    finally:
        opt.release.set()
        for tw in twins.values():
            tw.close()
    assert not _opt_threads()


def test_background_retuning_of_a_superseded_version_is_discarded():
    plant, cfg = _quiet_config()
    opt = _ScriptedOptimizer(hold=True)
    with DigitalTwin(plant, cfg, optimizer=opt, background=True) as twin:
        try:
            _to_closed_loop(twin)
            v2 = twin.updater.snapshot("rls-consolidation")
            k2 = twin.k
            twin.step()
            assert opt.entered.wait(30)  # version 2's tuning runs (held)
            v3 = twin.updater.snapshot("rls-consolidation")
            state = twin.step()
            assert {"model-version", "controller-rejected"} <= set(state.events)
            ev = _last(twin, "controller-rejected")
            assert ev.message == (f"discarded the MPC retuning for version {v2.version} "
                                  f"(submitted at sample {k2}): version {v3.version} superseded it")
            assert ev.payload["version"] == v2.version
            assert twin.optimizing  # version 3 waits until the worker is free
        finally:
            opt.release.set()
        state = _step_until(twin, "controller")
        assert _last(twin, "controller").message.startswith(f"MPC rebuilt on version {v3.version}")
        assert [t["version"] for t in twin.result().tunings] == [1, v3.version]
        assert opt.models[1:] == [v2.model, v3.model]
        assert twin.controller.model is v3.model and not twin.optimizing
    assert not _opt_threads()


def test_background_rejected_tuning_returns_to_the_validated_controller():
    plant, cfg = _quiet_config()
    with DigitalTwin(plant, cfg, optimizer=_ScriptedOptimizer(accept=False),
                     background=True) as twin:
        _to_closed_loop(twin)
        validated = twin.controller.model
        dm = twin.updater.snapshot("rls-consolidation")
        state = _step_until(twin, "controller-rejected")
        assert _last(twin, "controller-rejected").message == (
            "kept the controller: scripted rejection 1")
        # synchronously the controller would never have left the validated version
        assert twin.controller.model is validated is not dm.model
        _same_state(twin.controller, _rebuilt(twin, validated, cfg.mpc))
        assert math.isfinite(twin.step().command) and state.version == dm.version


def test_background_controller_that_cannot_be_built_is_kept(monkeypatch):
    plant, cfg = _quiet_config()
    with DigitalTwin(plant, cfg, optimizer=_ScriptedOptimizer(), background=True) as twin:
        _to_closed_loop(twin)
        running = twin.controller.problem

        def refuse(model, settings, **kwargs):
            raise DataError("DAQP setup failed (exit flag -1)")

        monkeypatch.setattr(controller_module, "build_mpc", refuse)  # in the worker too
        dm = twin.updater.snapshot("rls-consolidation")
        state = _step_until(twin, "controller-rejected")
        assert state.version == dm.version and twin.controller.problem is running
        assert "cannot be set up" in _last(twin, "controller-rejected").message
        for _ in range(5):
            assert math.isfinite(twin.step().command)


def test_close_joins_the_optimization_worker_with_a_job_in_flight():
    plant, cfg = _quiet_config()
    opt = _ScriptedOptimizer(hold=True)
    twin = DigitalTwin(plant, cfg, optimizer=opt, background=True)
    _to_closed_loop(twin)
    twin.updater.snapshot("rls-consolidation")
    twin.step()
    assert opt.entered.wait(30) and twin.optimizing and _opt_threads()
    timer = threading.Timer(0.2, opt.release.set)  # the tuning cannot be interrupted
    timer.start()
    try:
        twin.close()  # waits for the running tuning, drops its result
    finally:
        timer.cancel()
        opt.release.set()
    assert not twin.optimizing and not _opt_threads()
    assert [t["version"] for t in twin.result().tunings] == [1]  # its result was dropped


def test_synchronous_twin_starts_no_optimization_worker():
    plant, cfg = _quiet_config()
    opt = _ScriptedOptimizer()
    with DigitalTwin(plant, cfg, optimizer=opt) as twin:
        _to_closed_loop(twin)
        twin.updater.snapshot("rls-consolidation")
        assert "controller" in twin.step().events  # applied in the step, as before
        assert not twin.optimizing and twin.wait_optimization(0)
        assert opt.threads == ["MainThread", "MainThread"] and not _opt_threads()


# --------------------------------------------------------------------------- optimizer
def _first_order(pole=0.9, dt=0.1):
    return kt.KautzModel(kt.KautzBasis([pole], dt=dt, delayed=True), [1.0])


def test_optimizer_tunes_and_validates_mpc_weights():
    model = _first_order()
    settings = MPCSettings(30, 0.7, 3, 0.1, u_min=-1.0, u_max=1.0, du_max=0.5, y_max=2.0)
    opt = Optimizer(weight_factors=(0.1, 1.0, 10.0))
    tuning = opt.tune_controller(model, settings, step=0.5, u_op=0.0)
    assert tuning.accepted and len(tuning.candidates) == 3
    assert tuning.settings.r in {c.r for c in tuning.candidates if c.valid}
    best = min((c for c in tuning.candidates if c.valid), key=lambda c: c.score)
    assert tuning.settings.r == best.r
    # an output limit below the set-point cannot be met: nothing passes the validation
    tight = MPCSettings(30, 0.7, 3, 0.1, u_min=-1.0, u_max=1.0, du_max=0.5, y_max=0.2)
    rejected = opt.tune_controller(model, tight, step=0.5, u_op=0.0)
    assert not rejected.accepted and rejected.settings is tight


def test_mpc_settings_tighten_the_limits_by_the_dither():
    s = MPCSettings(40, 0.8, 4, 1.0, u_min=0.3, u_max=0.7, du_max=0.05, y_min=70, y_max=130,
                    dither=0.02)
    lim = s.controller_limits()
    assert (lim["u_min"], lim["u_max"]) == pytest.approx((0.32, 0.68))
    assert lim["du_max"] == pytest.approx(0.01) and lim["du_min"] == pytest.approx(-0.01)
    steps = s.constraint_steps()
    assert steps[:20].tolist() == list(range(20)) and steps[-1] < 40
    problem = build_mpc(_first_order(), s)
    assert problem.n_variables == 4
    with pytest.raises(DataError, match="dither"):
        MPCSettings(40, 0.8, 4, 1.0, u_min=0.3, u_max=0.7, du_max=0.03, dither=0.02)
    with pytest.raises(DataError, match="laguerre_pole"):
        MPCSettings(40, 1.2, 4, 1.0, u_min=0.0, u_max=1.0, du_max=0.1)


def test_controller_ignores_the_dither_it_injects():
    """The controller's feedback removes the predicted dither response: no reaction to it."""
    model = _first_order(0.8)
    s = MPCSettings(30, 0.6, 3, 0.1, u_min=-5.0, u_max=5.0, du_max=2.0, dither=0.5)
    ctl = MPCController()
    d = np.where(np.arange(40) % 10 < 5, 0.5, -0.5)
    ctl.rebuild(model, s, np.zeros(40), d)
    # the plant output is exactly the dither's response: the controller sees zero error
    x = np.zeros(1)
    for dk in d:
        x = model.basis.A @ x + model.basis.B * dk
    y = float(model.coefficients @ x)
    res = ctl.solve(y, 0.0, 0.0)
    assert abs(res.u_next) < 1e-9


# --------------------------------------------------------------------------- configuration
def test_parse_setpoints_forms_and_errors():
    assert parse_setpoints("1,2", start=0.0, end=10.0) == ((0.0, 1.0), (5.0, 2.0))
    assert parse_setpoints([(5, 2.0), (0, 1.0)], start=0, end=1) == ((0.0, 1.0), (5.0, 2.0))
    with pytest.raises(DataError, match="not both"):
        parse_setpoints("1,3:2", start=0.0, end=10.0)
    with pytest.raises(DataError, match="numbers"):
        parse_setpoints("1,x", start=0.0, end=10.0)
    with pytest.raises(DataError, match="empty"):
        parse_setpoints(" , ", start=0.0, end=10.0)


def test_config_validation_messages():
    with pytest.raises(DataError, match="outside the output limits"):
        TwinConfig.for_plant("hydraulic", setpoints="0.45,0.55")
    with pytest.raises(DataError, match="exceed the identification"):
        TwinConfig.for_plant("hydraulic", duration=5.0, ident_duration=6.0)
    with pytest.raises(DataError, match="unknown plant profile"):
        TwinConfig.for_plant("boiler")
    with pytest.raises(DataError, match="probability"):
        FaultConfig(dropout=1.5)
    with pytest.raises(DataError, match="cannot read"):
        FaultConfig.parse("noise=3")
    cfg = TwinConfig.for_plant("hydraulic", quick=True, faults="outlier=0.01")
    assert cfg.faults.outlier_size == 40.0  # the profile's default size
    assert cfg.setpoint(0.0) == 97.0 and cfg.setpoint(39.9) == 100.0
    assert json.loads(json.dumps(cfg.to_dict()))["mpc"]["dither"] == 0.02


def test_make_plant_names_and_errors(tmp_path):
    assert isinstance(make_plant("hydraulic"), HydraulicPlant)
    drifting = make_plant("hydraulic", drift=0.4, drift_events=(30.0, 60.0))
    assert drifting.drift_events == (30.0, 60.0)
    with pytest.raises(DataError, match="hydraulic plant only"):
        make_plant("tclab", drift=0.2)
    with pytest.raises(DataError, match="unknown plant"):
        make_plant("boiler")
    with pytest.raises(DataError, match="needs a file"):
        make_plant("replay:")


def test_replay_plant_is_monitored_without_control(tmp_path):
    rng = np.random.default_rng(3)
    u = np.repeat(0.5 + 0.02 * np.sign(rng.standard_normal(60)), 10)
    plant = HydraulicPlant(dt=0.02, temperature=30.0, noise=0.01, random_state=4)
    rec = run_open_loop(plant, u)
    y = rec.y.copy()
    y[400] = np.nan
    path = tmp_path / "rec.csv"
    np.savetxt(path, np.c_[rec.t, rec.u, y], delimiter=",", header="t,u,y", comments="")
    replay = make_plant(f"replay:{path}")
    cfg = TwinConfig.for_plant(replay, static_twin=False)
    assert not cfg.controlled and cfg.n_samples == 600
    run = DigitalTwin(replay, cfg).run(progress=False)
    m = compute_metrics(run)
    assert m["tracking_iae"] is None and m["constraint_violations"] == 0
    assert m["samples"]["dropouts"] == 1 and m["sync_fit_mean"] > 80.0
    np.testing.assert_allclose(run.arrays["u"], u)


# --------------------------------------------------------------------------- report
def test_rolling_fit_windows():
    y = np.arange(20, dtype=float)
    ends, fits = rolling_fit(y, y, 10, 5, start=2)
    assert ends.tolist() == [12, 17] and np.all(fits == 100.0)
    y2 = y.copy()
    y2[:] = np.nan
    assert np.isnan(rolling_fit(y2, y, 10, 5)[1]).all()


def test_write_report_files(tclab_run, tmp_path):
    run, _ = tclab_run
    paths = write_report(run, tmp_path / "rep", command="kautztwin twin run --plant tclab")
    names = sorted(p.name for p in (tmp_path / "rep").iterdir())
    assert names == ["metrics.json", "outputs.png", "report.md", "sync_fit.png", "timings.png",
                     "tracking.png"]
    text = paths["report"].read_text()
    assert "## Acceptance checks" in text
    assert "![MPC tracking with constraints](tracking.png)" in text
    metrics = json.loads(paths["metrics"].read_text())
    assert metrics["acceptance"]["zero_constraint_violations"] is True


@pytest.mark.slow
def test_acceptance_full_hydraulic_drift_run():
    """Issue acceptance: 90 s, 40 % dominant-pole drift at 30 s and 60 s, 15 s recovery windows."""
    plant = make_plant("hydraulic", drift=0.4, drift_events=(30.0, 60.0), seed=0)
    cfg = TwinConfig.for_plant(plant)
    m = compute_metrics(DigitalTwin(plant, cfg).run(progress=False))
    print(json.dumps({k: m[k] for k in METRIC_KEYS}, indent=1))
    assert all(m["acceptance"].values()), m["acceptance"]


class _FakeDNN:
    """Stands in for a trained estimator: only its name matters here."""

    def __init__(self, name):
        self.name = name

    def predict_models(self, responses, t=None):  # pragma: no cover - not called
        raise NotImplementedError


class _RetrainRecorder(Optimizer):
    """The default optimizer with a scripted estimator retraining (no network training)."""

    def __init__(self, outcome):
        super().__init__()
        self.outcome = outcome
        self.calls = []

    def retrain_estimator(self, estimator, model, **kwargs):
        from kautztwin.twin import EstimatorRetraining

        self.calls.append((estimator, model))
        if isinstance(self.outcome, Exception):
            raise self.outcome
        new = _FakeDNN(f"{estimator.name}+1")
        return EstimatorRetraining(
            accepted=self.outcome, estimator=new if self.outcome else estimator, candidate=new,
            fit_old=80.0, fit_new=90.0 if self.outcome else 70.0, reason="scripted",
        )


@pytest.mark.parametrize(
    ("outcome", "event", "after"),
    [
        (True, "estimator-update", "dnn-0+1"),
        (False, "estimator-rejected", "dnn-0"),
        (DataError("the estimator has 4 functions, the model 3"), "estimator-rejected", "dnn-0"),
    ],
)
def test_new_model_versions_ask_the_optimizer_to_retrain_the_estimator(outcome, event, after):
    plant, cfg = _config()
    optimizer = _RetrainRecorder(outcome)
    dnn = _FakeDNN("dnn-0")
    with DigitalTwin(plant, cfg, optimizer=optimizer, estimator=dnn) as twin:
        twin.start()
        while twin.k <= twin.config.n_ident:
            twin.step()
        assert twin.updater.dnn is dnn and not optimizer.calls  # version 1: no retraining
        dm = twin.updater.snapshot("rls-consolidation")  # a new version
        state = twin.step()
        assert [(e, m.coefficients.tolist()) for e, m in optimizer.calls] == [
            (dnn, dm.model.coefficients.tolist())]
        assert event in state.events
        assert twin.updater.dnn.name == after and twin.estimator is twin.updater.dnn
        for _ in range(5):
            assert math.isfinite(twin.step().command)
        metrics = compute_metrics(twin.result())
    accepted = int(event == "estimator-update")
    assert metrics["estimator_retrainings"] == {"accepted": accepted, "rejected": 1 - accepted}


class _HeldRetraining(_RetrainRecorder):
    """The scripted retraining, held in the worker until ``release`` is set."""

    def __init__(self, outcome):
        super().__init__(outcome)
        self.entered, self.release = threading.Event(), threading.Event()

    def retrain_estimator(self, estimator, model, **kwargs):
        self.entered.set()
        if not self.release.wait(30):  # pragma: no cover - only when the test fails
            raise TwinError("the test never released the retraining")
        return super().retrain_estimator(estimator, model, **kwargs)


@pytest.mark.parametrize(
    ("outcome", "event", "after"),
    [
        (True, "estimator-update", "dnn-0+1"),
        (DataError("the estimator has 4 functions, the model 3"), "estimator-rejected", "dnn-0"),
    ],
    ids=["accepted", "error"],
)
def test_background_estimator_retraining_is_applied_later(outcome, event, after):
    plant, cfg = _quiet_config()
    optimizer = _HeldRetraining(outcome)
    dnn = _FakeDNN("dnn-0")
    with DigitalTwin(plant, cfg, optimizer=optimizer, estimator=dnn, background=True) as twin:
        try:
            _to_closed_loop(twin)
            dm = twin.updater.snapshot("rls-consolidation")
            k_new = twin.k
            twin.step()
            assert optimizer.entered.wait(30)
            for _ in range(5):  # held in the worker: the running estimator stays
                state = twin.step()
                assert event not in state.events and twin.updater.dnn is dnn
        finally:
            optimizer.release.set()
        state = _step_until(twin, event)
        assert [(e, m) for e, m in optimizer.calls] == [(dnn, dm.model)]
        assert twin.updater.dnn.name == after and twin.estimator is twin.updater.dnn
        assert _last(twin, "estimator").payload["k_submitted"] == k_new < state.k
        metrics = compute_metrics(twin.result())
    accepted = int(event == "estimator-update")
    assert metrics["estimator_retrainings"] == {"accepted": accepted, "rejected": 1 - accepted}
    assert not _opt_threads()


def test_a_config_pickles_to_an_equal_config():
    # a process pool (the fleet's workers, a Ray shard) gets its copy by pickle
    import pickle

    cfg = TwinConfig.for_plant("hydraulic", quick=True, seed=3, drift_events=(5.0,))
    copy = pickle.loads(pickle.dumps(cfg))
    assert copy == cfg and copy.to_dict() == cfg.to_dict()
    with pytest.raises(TypeError):
        copy.updater["max_iter"] = 1  # still read-only
