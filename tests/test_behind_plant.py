"""A live twin that is behind its plant (issue #11): inputs in flight, wire latency, dither.

The oracle is a plant that really runs ``Q`` samples ahead of the loop (the link holds ``Q``
newer samples, ``meta['queued'] == Q``) and whose in-order wire applies each input ``L``
periods after the plant's newest sample when it was sent: the input delay of a decision is
then exactly ``Q + L`` samples, and every input sent is applied in order (the newest that
has arrived), so the rate limit can be checked period by period at the plant.
"""

from __future__ import annotations

from collections import deque

import numpy as np
import pytest

import kautztwin as kt
from kautztwin.twin.runtime.inflight import InputsInFlight


# ---------------------------------------------------------------------- InputsInFlight
def test_latency_is_learnt_from_the_sample_stream():
    f = InputsInFlight(max_wait=50)
    assert f.delay(queued=7) is None  # nothing learnt: the link's estimate is used
    # sent after reading 100 with 20 newer samples held: the plant was at sample 120;
    # applied over period 123, which the reading of sample 124 reports
    f.send(0.6, k=100, queued=20, applied=0.5)
    for k in range(101, 124):
        assert f.awaiting(k, applied=0.5, queued=20)
    assert not f.awaiting(124, applied=0.6, queued=20)
    assert list(f.latencies) == [3] and f.delay(queued=20) == 23 and not f.pending


def test_an_old_sample_with_the_same_value_does_not_confirm():
    """A loop that is behind reads past inputs: a dither takes the same values again."""
    f = InputsInFlight(max_wait=500)
    f.send(0.6, k=100, queued=50, applied=0.5)
    # readings 101..150 show an earlier 0.6 (applied before the send): not this input
    for k in range(101, 151):
        applied = 0.6 if k % 20 < 10 else 0.5
        assert f.awaiting(k, applied=applied, queued=50)
    assert not f.latencies


def test_an_input_never_seen_is_given_up_after_max_wait():
    f = InputsInFlight(max_wait=10)
    f.send(0.6, k=0, queued=0, applied=0.5)
    assert f.awaiting(10, applied=0.5, queued=0)
    assert not f.awaiting(11, applied=0.5, queued=0)


# ---------------------------------------------------------------------- the loop
class _AheadPlant:
    """A live plant ``ahead`` samples ahead of the loop, with an in-order wire of ``wire``."""

    connected = True  # a live plant: the loop pairs samples with the inputs applied

    def __init__(self, plant, ahead: int, wire: int) -> None:
        self.p, self.ahead, self.wire_delay = plant, ahead, wire
        self.dt, self.name, self.input_limits = plant.dt, plant.name, plant.input_limits

    def _period(self) -> kt.twin.Reading:
        """Simulate period ``self.n`` with the newest input that has arrived."""
        while self.wire and self.wire[0][0] <= self.n:
            self.u = self.wire.popleft()[1]
        self.applied.append(self.u)
        r = self.p.step(self.u)
        self.n += 1
        return kt.twin.Reading(r.t, r.y, {**r.meta, "u": self.u, "u_applied": self.u})

    def reset(self):
        self.u, self.n, self.applied = 0.5, 0, []
        self.wire: deque[tuple[int, float]] = deque()
        first = self.p.reset()
        self.buffer = deque(self._period() for _ in range(self.ahead))
        return self._out(first)

    def _out(self, r):
        return kt.twin.Reading(r.t, r.y, {**r.meta, "queued": self.ahead,
                                          "input_delay": self.ahead + self.wire_delay})

    def step(self, u):
        # the plant's newest sample is self.n: the input is applied from period n + wire on
        self.wire.append((self.n + self.wire_delay, float(u)))
        self.buffer.append(self._period())
        return self._out(self.buffer.popleft())

    def close(self) -> None:
        self.p.close()


def _run_behind(monkeypatch=None, old_hold: bool = False):
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    from kautztwin.twin.runtime.loop import DigitalTwin as Loop

    if old_hold:  # the loop before: the dither held with the command while behind
        monkeypatch.setattr(Loop, "_held_dither", lambda self, k: self._d_prev)
    plant = _AheadPlant(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1),
                        ahead=40, wire=3)
    cfg = TwinConfig.for_plant("hydraulic", duration=30.0, quick=True, static_twin=False,
                               setpoints=((0.0, 97.0), (20.0, 101.0)))
    twin = DigitalTwin(plant, cfg, background=False)
    run = twin.run(progress=False)
    return twin, plant, run, cfg


def _longest_flat(u: np.ndarray) -> int:
    change = np.flatnonzero(np.diff(u) != 0)
    edges = np.concatenate([[-1], change, [u.size - 1]])
    return int(np.max(np.diff(edges)))


def test_behind_loop_keeps_the_plant_excited_within_the_rate_limit(monkeypatch):
    twin, plant, run, cfg = _run_behind()
    mpc = cfg.mpc
    k0 = run.k_closed_loop
    applied = np.asarray(plant.applied)
    u = applied[k0 + 40 + 3:]  # the closed loop's inputs, at the plant
    # the rate and level limits hold period by period at the plant
    assert np.max(np.abs(np.diff(u))) <= mpc.du_max + 1e-12
    assert mpc.u_min <= u.min() and u.max() <= mpc.u_max
    # the loop learnt the delay from the stream: queue + wire, exactly
    assert twin._input_delay(run.n_done - 1) == 40 + 3
    # the dither goes on while the loop holds its command: the plant's input changes at
    # least once per longest dither hold (25 samples) plus the wire and the confirmation
    bound = max(cfg.dither_hold) + 3 + 1
    assert _longest_flat(u) <= bound
    # and it tracks the set-point step under a 43-sample delay
    assert abs(np.mean(run.arrays["y"][-100:]) - 101.0) < 2.0
    # the loop before (dither held with the command): flat for longer
    _, plant_old, run_old, _ = _run_behind(monkeypatch, old_hold=True)
    u_old = np.asarray(plant_old.applied)[run_old.k_closed_loop + 43:]
    assert _longest_flat(u_old) > bound


@pytest.mark.parametrize("applied, latencies", [(float("nan"), [1]), (0.5, [])])
def test_confirmation_needs_a_change_to_measure(applied, latencies):
    """An input equal to what the plant applies already is confirmed without a latency."""
    f = InputsInFlight(max_wait=50)
    f.send(0.5, k=10, queued=0, applied=applied)
    assert not f.awaiting(12, applied=0.5, queued=0)  # period 11, one past the newest (10)
    assert not f.pending and list(f.latencies) == latencies


# ---------------------------------------------------------------------- process worker
def _job():
    """A re-identification job on a known second-order plant (scipy.signal simulates it)."""
    from scipy import signal

    from kautztwin.twin.update.worker import _ReidJob

    dt = 0.02
    rng = np.random.default_rng(0)
    u = 0.5 + 0.05 * np.sign(rng.standard_normal(700))
    den = np.poly([0.97, 0.9])  # discrete poles: rates 1.5 and 5.3 1/s at dt = 0.02 s
    y = 100.0 + signal.lfilter([0.0, 0.5, 0.2], den, u - 0.5)
    y += 0.001 * rng.standard_normal(700)
    u.flags.writeable = y.flags.writeable = False
    return _ReidJob(u=u, y=y, w0=200, n_est=600, n_val=100,
                    poles=np.array([-1.5 + 0j, -5.0 + 0j]), dt=dt, input_offset=0.5,
                    min_rate=None, max_iter=30, k=700)


def test_process_worker_computes_the_thread_workers_candidate():
    from kautztwin.twin.update.worker import _fit_window, _ReidWorker

    job = _job()
    here = _fit_window(job).fit
    worker = _ReidWorker("process")
    try:
        worker.prestart()
        worker.submit(job)
        assert worker.wait(120)
        done = worker.take_finished()
    finally:
        worker.close()
    there = worker.result(done).fit
    assert here.fit_percent > 90.0  # a real fit (second-order plant, two poles)
    np.testing.assert_allclose(there.model.coefficients, here.model.coefficients,
                               rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(there.model.basis.poles, here.model.basis.poles,
                               rtol=1e-9, atol=1e-12)
    assert there.offset == pytest.approx(here.offset, rel=1e-12)
    assert worker.closed and worker.pending is None


def test_updater_worker_is_checked():
    from kautztwin.exceptions import DataError
    from kautztwin.twin import Updater

    model = kt.KautzModel(kt.KautzBasis([0.9], dt=0.1, delayed=True), [1.0])
    with pytest.raises(DataError, match="worker must be 'thread' or 'process'"):
        Updater(model, dt=0.1, worker="fiber")


def test_samples_queued_during_the_identification_are_not_adapted_on():
    """The catch-up samples carry one held input: the estimator predicts them, learns nothing."""
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    from test_delay_compensation import _Backlog

    cfg = TwinConfig.for_plant("hydraulic", duration=12.0, quick=True, static_twin=False)
    n_id, backlog = cfg.n_ident, 60
    twin = DigitalTwin(_Backlog(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01,
                                               random_state=1), n_id, backlog), cfg,
                       background=False)
    twin.start()
    coefs = {}
    while twin.k < n_id + backlog + 20:
        twin.step()
        coefs[twin.k - 1] = twin.updater.estimator_.coef_.copy() if twin.updater else None
    k_cl = twin.result().k_closed_loop
    twin.close()
    assert k_cl == n_id + backlog - 5
    # from the identification's sample to the last one before the closed loop: unchanged
    for k in range(n_id, k_cl):
        np.testing.assert_array_equal(coefs[k], coefs[n_id])
    assert twin.updater.fast_update  # switched back on
    # the closed loop adapts again
    assert not np.array_equal(coefs[k_cl + 10], coefs[n_id])
