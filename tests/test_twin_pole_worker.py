"""The resync pole re-optimisation off the sample thread (twin/optimization/poles.py)."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from kautztwin.twin.optimization import Optimizer
from kautztwin.twin.optimization import poles as poles_module
from kautztwin.twin.optimization.poles import (
    PoleWorker,
    judge_pole_candidate,
    pole_candidate,
    pole_job,
)
from kautztwin.twin.runtime import DigitalTwin, TwinConfig, make_plant
from kautztwin.twin.update import RecursiveKautzEstimator, Updater

DT = 0.05
POLES = np.exp(np.array([-2.0, -5.0]) * DT)  # the twin's model: a 2nd-order cascade
POLES_SLOW = np.exp(np.array([-1.0, -5.0]) * DT)  # the plant after a drift: slow pole halved


def _binary(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    out: list[float] = []
    while len(out) < n:
        out += [float(rng.choice([-1.0, 1.0]))] * int(rng.integers(3, 15))
    return np.array(out[:n])


def _cascade(u: np.ndarray, poles: np.ndarray) -> np.ndarray:
    """Unit-gain first-order lags in series, gain 2, offset 3 (an independent simulation)."""
    x = np.zeros(poles.size)
    y = np.empty(u.size)
    for k in range(u.size):
        y[k] = 2.0 * x[-1] + 3.0
        inp = u[k]
        for i, a in enumerate(poles):
            x[i], inp = a * x[i] + (1 - a) * inp, x[i]
    return y


def _drifted_updater() -> Updater:
    """A twin fitted on the nominal plant whose fast path has followed the drifted one."""
    u0 = _binary(600, 10)
    model = RecursiveKautzEstimator(POLES, dt=DT, forgetting=1.0, delta=1e8).fit(
        u0, _cascade(u0, POLES)).model_
    # the fast path's extra pole (at half the slowest rate) lets it follow the drift
    upd = Updater(model, dt=DT, offset=3.0, reidentify=False, reid_samples=200, burn_in=100,
                  forgetting=0.98, extra_poles=[-1.0])
    u = _binary(800, 3)
    for uk, yk in zip(u, _cascade(u, POLES_SLOW), strict=True):
        upd.step(uk, yk)
    return upd


def _same_update(a, b) -> None:
    assert (a.kind, a.accepted, a.reason) == (b.kind, b.accepted, b.reason)
    assert (a.fit_candidate, a.fit_current, a.offset) == (b.fit_candidate, b.fit_current, b.offset)
    np.testing.assert_array_equal(a.candidate.basis.poles, b.candidate.basis.poles)
    np.testing.assert_array_equal(a.candidate.coefficients, b.candidate.coefficients)


def test_the_split_re_optimisation_is_the_synchronous_one_bit_for_bit():
    opt = Optimizer()
    sync, split = _drifted_updater(), _drifted_updater()
    mu_sync = opt.retune_model(sync)
    job = pole_job(opt, split, split.k)
    out = pole_candidate(job)
    mu = judge_pole_candidate(split, job, out)
    # the drift is learnt: the candidate has the drifted plant's rates (1 and 5 per second)
    assert mu_sync is not None and mu_sync.accepted
    rates = np.sort(-np.log(np.abs(mu_sync.candidate.basis.poles)) / DT)
    np.testing.assert_allclose(rates, [1.0, 5.0], rtol=1e-3)
    _same_update(mu, mu_sync)
    assert mu.k_submitted == job.k
    assert split.digital_model.version == sync.digital_model.version == 2
    np.testing.assert_array_equal(split.digital_model.model.coefficients,
                                  sync.digital_model.model.coefficients)
    assert split.counts == sync.counts
    np.testing.assert_array_equal(split.predict(np.ones(50)), sync.predict(np.ones(50)))


def test_a_late_judgement_scores_the_candidate_on_the_window_frozen_at_the_resync():
    opt = Optimizer()
    now, late = _drifted_updater(), _drifted_updater()
    job_now = pole_job(opt, now, now.k)
    mu_now = judge_pole_candidate(now, job_now, pole_candidate(job_now))
    job = pole_job(opt, late, late.k)
    out = pole_candidate(job)
    u = _binary(900, 3)  # _drifted_updater's input, continued: 60 samples arrive meanwhile
    y = _cascade(u, POLES_SLOW)
    for uk, yk in zip(u[800:860], y[800:860], strict=True):
        late.step(uk, yk)
    mu = judge_pole_candidate(late, job, out)
    # the candidate is scored on the frozen window: exactly the immediate judgement's fit,
    # against the live model of now (which has learnt the 60 samples since)
    assert mu.fit_candidate == mu_now.fit_candidate > 99.0
    assert (mu.k, mu.k_submitted) == (late.k, job.k) and late.k == job.k_updater + 60
    assert job.n_val == int(late.validation_fraction * late.reid_samples)


def test_a_job_is_frozen_and_the_process_worker_returns_the_same_candidate():
    opt = Optimizer()
    upd = _drifted_updater()
    job = pole_job(opt, upd, upd.k)
    assert not job.y.flags.writeable and not job.poles.flags.writeable
    local = pole_candidate(job)
    # the portable form rebuilds the candidate exactly (what crosses the process boundary)
    back = poles_module._from_portable(poles_module._pole_candidate_portable(job))
    worker = PoleWorker("process")
    try:
        pending = worker.submit(job)
        pending.future.result(timeout=120)
        assert worker.done(pending)
        remote = worker.outcome(pending)
    finally:
        worker.close()
    for other in (back, remote):
        np.testing.assert_array_equal(other.model.basis.poles, local.model.basis.poles)
        np.testing.assert_array_equal(other.model.coefficients, local.model.coefficients)
    assert pole_job(Optimizer(retune_poles=False), upd, upd.k) is None
    with pytest.raises(ValueError, match="'thread' or 'process'"):
        PoleWorker("fork")


def _drift_config():
    """A drifting plant; no re-identification (its background attempts would be judged at
    other samples in a replay): the versions come from the fast path and the pole retuning."""
    plant = make_plant("hydraulic", drift=0.4, drift_events=(8.0, 16.0), seed=0)
    cfg = TwinConfig.for_plant(plant, duration=60.0, quick=True, static_twin=False)
    return plant, replace(cfg, updater={**cfg.updater, "reidentify": False})


def _pole_events(events, k_max=None):
    return [(e.kind, e.k, e.message, e.payload.get("k_submitted")) for e in events
            if (e.kind == "pole-retune" or e.message.startswith("pole re-optimisation"))
            and (k_max is None or e.k < k_max)]


@pytest.mark.parametrize("stop", ["after-judgement", "before-judgement"])
def test_background_twin_judges_the_candidate_later_and_a_resume_replays_it(tmp_path, stop):
    store = tmp_path / "h.sqlite"
    plant, cfg = _drift_config()
    twin = DigitalTwin(plant, cfg, history=store, background=True)
    twin.start()
    submitted = judged = None
    while twin.k < cfg.n_samples:
        state = twin.step()
        if "pole-retune" in state.events and submitted is None:
            submitted = state.k
            assert "model-update" not in state.events  # nothing judged on the sample thread
            if stop == "before-judgement":
                break
        if submitted is not None and state.k > submitted and any(
                e[3] == submitted and e[0] != "pole-retune"
                for e in _pole_events(twin._record.events)):
            judged = state.k
            for _ in range(50):
                twin.step()
            break
    assert submitted is not None
    stop_k = twin.k
    original = _pole_events(twin._record.events)
    versions = twin._record.arrays["version"][:stop_k].copy()
    twin.finish()
    twin.close()
    if stop == "after-judgement":
        assert judged is not None and judged > submitted
        judgement = next(e for e in original if e[3] == submitted and e[0] != "pole-retune")
        assert judgement[1] == judged and judgement[2].startswith("pole re-optimisation: ")
    plant2, cfg2 = _drift_config()
    with DigitalTwin(plant2, cfg2, history=store, background=True) as resumed:
        resumed.start()  # replays the committed samples synchronously
        assert resumed.k == stop_k
        replayed = _pole_events(resumed._record.events)
        np.testing.assert_array_equal(resumed._record.arrays["version"][:stop_k], versions)
        if stop == "after-judgement":
            assert replayed == original  # the same samples, the same fits in the messages
        else:
            assert replayed == original  # the submission; the candidate waits for the live run
            state = resumed.step()  # the first live sample judges it
            late = _pole_events(resumed._record.events)[len(replayed):]
            assert [(e[0] != "pole-retune", e[1], e[3]) for e in late][:1] == [
                (True, stop_k, submitted)]
            assert state.k == stop_k



def test_worker_processes_fork_from_a_server_that_imported_the_job_modules():
    """The forkserver preloads the modules that run jobs in workers (``preload_in_workers``).

    Each worker process used to import the library when it started (about 1 s of CPU,
    which on the 2-core host fell on a live twin's closed-loop start); now the forkserver
    imports it once and the workers fork with it.  Checked on the context the workers
    are started with (the preload list of the standard library's forkserver).
    """
    import multiprocessing.forkserver

    import kautztwin.twin.optimization.background  # noqa: F401  (registers itself)
    import kautztwin.twin.optimization.poles  # noqa: F401  (registers itself)
    from kautztwin.twin.update.worker import _process_context

    ctx = _process_context()
    assert ctx.get_start_method() == "forkserver"
    preload = multiprocessing.forkserver._forkserver._preload_modules
    assert {"__main__", "kautztwin.twin.update.worker", "kautztwin.twin.optimization.poles",
            "kautztwin.twin.optimization.background"} <= set(preload)
