"""The MPC's predictor over a known input delay (issue #11: a live plant applies inputs late).

Oracle (a Smith predictor's defining property): with an exact model, no disturbance and the
plant at rest, the loop whose plant applies each input ``d`` samples late (and reports the
input it applied, as the live links do), controlled with ``delay=d``, makes the delay-free
loop's decisions, and its outputs are the delay-free loop's shifted by ``d`` samples.
"""

from __future__ import annotations

import numpy as np
import pytest

import kautztwin as kt
from kautztwin.twin.prediction import MPCController, MPCSettings

U0, Y0 = 0.5, 10.0  # the input operating point and the output at rest


def _model() -> kt.KautzModel:
    return kt.KautzModel(kt.KautzBasis([0.9, 0.6], dt=0.1, delayed=True), [1.0, 0.5])


def _loop(delay: int, compensate: bool, n: int = 120) -> tuple[np.ndarray, np.ndarray]:
    """Closed loop on the exact model whose input arrives ``delay`` samples late."""
    model = _model()
    A, B, c = np.array(model.basis.A), np.array(model.basis.B), np.array(model.coefficients)
    ctl = MPCController(input_offset=U0)
    settings = MPCSettings(30, 0.7, 3, 0.1, u_min=0.0, u_max=1.0, du_max=0.2,
                           y_min=0.0, y_max=12.0)
    ctl.rebuild(model, settings, np.full(50, U0), np.zeros(50))  # the plant at rest before
    x = np.zeros(A.shape[0])
    sent = [U0] * delay  # inputs on their way to the plant
    y_log, v_log = [], []
    v_prev = U0
    for k in range(n):
        y = float(c @ x) + Y0
        ref = Y0 + (1.0 if k >= 5 else 0.0)
        res = ctl.solve(y, ref, v_prev, delay=delay if compensate else 0)
        v = float(res.u_next)
        ctl.advance(v, 0.0)
        sent.append(v)
        applied = sent.pop(0)  # the plant applies the input sent `delay` samples ago
        x = A @ x + B * (applied - U0)
        ctl.revise_last_input(applied - v)  # and reports it (u_applied), as a live link does
        y_log.append(y)
        v_log.append(v)
        v_prev = v
    return np.array(y_log), np.array(v_log)


@pytest.mark.parametrize("delay", [1, 4, 10], ids=["d1", "d4", "d10"])
def test_delayed_loop_is_the_delay_free_loop_shifted(delay):
    y0, v0 = _loop(0, compensate=False)
    y, v = _loop(delay, compensate=True)
    # the outputs are the delay-free loop's, shifted by the delay
    np.testing.assert_allclose(y[delay:], y0[:-delay], rtol=0, atol=1e-9)
    # the decision at step k is the delay-free loop's decision at k (made d periods ahead)
    np.testing.assert_allclose(v, v0, rtol=0, atol=1e-9)
    assert np.ptp(y0) > 0.5  # the set-point step was tracked: the oracle is not trivial


def test_without_the_predictor_the_delayed_loop_differs():
    y0, _ = _loop(0, compensate=False)
    y, _ = _loop(10, compensate=False)
    assert np.max(np.abs(y[10:] - y0[:-10])) > 0.05


def test_delay_beyond_the_inputs_issued_is_capped():
    model = _model()
    ctl = MPCController(input_offset=U0)
    ctl.rebuild(model, MPCSettings(30, 0.7, 3, 0.1, u_min=0.0, u_max=1.0, du_max=0.2),
                np.full(3, U0), np.zeros(3))
    # three inputs known: a delay of 100 predicts over those three, as a delay of 3 does
    a, b = ctl.solve(Y0, Y0 + 1.0, U0, delay=100), ctl.solve(Y0, Y0 + 1.0, U0, delay=3)
    assert a.u_next == b.u_next


class _LateInputs:
    """A plant whose inputs arrive 1..7 samples late, in order but overtaken (the newest wins).

    It reports the input it applied over each period (``u_applied``) and an estimate of the
    delay (``input_delay``), as the live links do.
    """

    connected = True  # a live plant: the loop pairs samples with the inputs applied

    def __init__(self, plant, seed: int = 0) -> None:
        self.p = plant
        self.dt, self.name, self.input_limits = plant.dt, plant.name, plant.input_limits
        self.rng = np.random.default_rng(seed)
        self.applied: list[float] = []

    def reset(self):
        self.k, self.wire, self.u = 0, [], 0.5
        return self.p.reset()

    def step(self, u):
        self.wire.append((self.k + int(self.rng.integers(1, 8)), float(u)))
        arrived = [w for w in self.wire if w[0] <= self.k]
        if arrived:  # the newest input that has arrived (an older one still on its way is lost)
            newest = max(arrived)
            self.u = newest[1]
            self.wire = [w for w in self.wire if w[0] > newest[0]]
        self.k += 1
        self.applied.append(self.u)
        r = self.p.step(self.u)
        return kt.twin.Reading(r.t, r.y, {**r.meta, "u": self.u, "u_applied": self.u,
                                          "input_delay": 4, "queued": 0})

    def close(self) -> None:
        self.p.close()


def test_live_loop_keeps_the_rate_limit_at_the_plant():
    """Inputs overtaken on the wire would jump the rate limit: the loop waits for each one."""
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.report import compute_metrics
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig

    plant = _LateInputs(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1))
    cfg = TwinConfig.for_plant("hydraulic", duration=16.0, quick=True, static_twin=False,
                               setpoints=((0.0, 97.0), (8.0, 103.0)))
    run = DigitalTwin(plant, cfg, background=False).run(progress=False)
    m = compute_metrics(run)
    mpc = cfg.mpc
    k0 = run.k_closed_loop
    u = np.asarray(plant.applied)[k0:]  # what the plant applied, period by period
    assert np.max(np.abs(np.diff(u))) <= mpc.du_max + 1e-12
    assert mpc.u_min <= u.min() and u.max() <= mpc.u_max
    assert m["constraint_violations"] == 0
    # and it tracks: the last 2 s lie closer to the new set-point than half the 6 rad/s step
    y_end = run.arrays["y"][-100:]
    assert abs(np.mean(y_end) - 103.0) < 3.0, np.mean(y_end)
    # the stored inputs are the applied ones (the sample pairs the plant saw)
    np.testing.assert_array_equal(run.arrays["u"][: len(plant.applied)], plant.applied)


class _Backlog(_LateInputs):
    """A live plant whose link reports a backlog after the identification (``meta['queued']``).

    The readings after sample ``start`` say ``backlog`` newer samples wait, one fewer each
    sample: as after an identification that stalled the loop while the plant went on.
    """

    def __init__(self, plant, start: int, backlog: int) -> None:
        super().__init__(plant)
        self.start, self.backlog = start, backlog

    def step(self, u):
        r = super().step(u)
        queued = max(0, self.backlog - (self.k - self.start)) if self.k > self.start else 0
        return kt.twin.Reading(r.t, r.y, {**r.meta, "input_delay": 1 + queued,
                                          "queued": queued})


def test_live_loop_starts_the_closed_loop_once_it_has_caught_up():
    """The samples queued during the identification are taken holding its last input."""
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    from kautztwin.twin.runtime.loop import MAX_QUEUED

    cfg = TwinConfig.for_plant("hydraulic", duration=12.0, quick=True, static_twin=False)
    n_id, backlog = cfg.n_ident, 60

    twins = []

    def run(plant):
        twins.append(DigitalTwin(plant, cfg, background=False))
        return twins[-1].run(progress=False)

    plant = _Backlog(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1),
                     n_id, backlog)
    live = run(plant)
    # the reading of n_id predates the stall; the first one with <= MAX_QUEUED waiting:
    k_cl = n_id + backlog - MAX_QUEUED
    assert live.k_closed_loop == k_cl
    a = live.arrays
    assert np.all(np.isnan(a["mpc_ms"][n_id:k_cl])) and np.all(a["dither"][n_id:k_cl] == 0)
    assert np.isfinite(a["mpc_ms"][k_cl])  # the first decision
    # the identification's last input, the excitation's centre, held (once the inputs on
    # the wire, <= 7 samples, land): the plant waits at the identified operating point
    applied = np.asarray(plant.applied)
    assert np.all(applied[n_id + 8:k_cl] == cfg.ident_level) and k_cl > n_id + 40
    assert abs(applied[n_id - 1] - cfg.ident_level) == pytest.approx(cfg.ident_amplitude)
    assert np.ptp(applied[k_cl:k_cl + 100]) > 0  # then the controller moves it
    # the first controller was tuned before the first closed-loop sample
    assert next(e.k for e in live.events if e.kind == "controller") == n_id
    # the monitor judged none of the queued samples: its first window after the
    # identification is the closed loop's first window
    ends = twins[-1].updater.monitor.history.k
    assert ends[ends >= n_id - 1].min() == k_cl + cfg.monitor_window - 1, ends
    assert np.all(np.isfinite(live.arrays["y_pred"][n_id:k_cl]))  # the twin took them
    starts = [e.payload["k_closed_loop"] for e in live.events
              if e.kind == "phase" and "k_closed_loop" in e.payload]
    assert starts == [k_cl]
    # no backlog: the closed loop starts right after the identification's sample
    plain = run(_LateInputs(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01,
                                           random_state=1)))
    assert plain.k_closed_loop == n_id + 1
    # a simulated plant (the offline run): at once
    sim = run(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1))
    assert sim.k_closed_loop == n_id


def test_fast_path_restarts_its_covariance_at_a_live_closed_loop_start(monkeypatch):
    """A live plant's closed loop starts with the fast path's covariance back at delta I.

    Only there: a simulated plant's closed loop starts at ``n_ident``, where the twin is
    built, and keeps the covariance of the twin's catch-up (its runs are unchanged).
    """
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig
    from kautztwin.twin.update.recursive import RecursiveKautzEstimator

    cfg = TwinConfig.for_plant("hydraulic", duration=12.0, quick=True, static_twin=False)
    n_id, backlog = cfg.n_ident, 60
    restarts: list[np.ndarray] = []
    original = RecursiveKautzEstimator.reset_covariance

    def spy(self, delta=None):
        restarts.append(self.covariance_)  # the covariance it replaces
        original(self, delta)

    monkeypatch.setattr(RecursiveKautzEstimator, "reset_covariance", spy)

    def steps(plant, until):
        """``{k: restarts during the step of sample k}`` and the twin."""
        twin = DigitalTwin(plant, cfg, background=False)
        twin.start()
        seen = {}
        while twin.k < until:
            k, before = twin.k, len(restarts)
            twin.step()
            if len(restarts) > before:
                seen[k] = len(restarts) - before
        return seen, twin

    seen, twin = steps(_Backlog(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01,
                                               random_state=1), n_id, backlog),
                       n_id + backlog + 100)
    k_cl = twin.result().k_closed_loop
    assert k_cl > n_id + 40 and seen == {k_cl: 1}, (seen, k_cl)
    est = twin.updater.estimator_
    replaced = restarts[-1]
    # what it replaced had adapted far from delta I over the identification's samples
    assert not np.allclose(replaced, est.delta * np.eye(replaced.shape[0]), rtol=0.1)
    twin.close()
    restarts.clear()
    seen, twin = steps(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1),
                       n_id + 100)
    assert twin.result().k_closed_loop == n_id and seen == {}
    twin.close()


def test_resumed_live_run_replays_the_closed_loop_start(tmp_path):
    """A resumed live run starts its closed loop at the stored sample, not at n_ident."""
    from kautztwin.twin import HydraulicPlant
    from kautztwin.twin.runtime import DigitalTwin, TwinConfig

    cfg = TwinConfig.for_plant("hydraulic", duration=12.0, quick=True, static_twin=False)
    n_id, backlog = cfg.n_ident, 60

    def plant():
        return _Backlog(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1),
                        n_id, backlog)

    store = tmp_path / "h.sqlite"
    twin = DigitalTwin(plant(), cfg, history=store, background=False)
    twin.start()
    while twin.k < n_id + backlog + 50:
        twin.step()
    k_cl = twin.result().k_closed_loop
    twin.finish()
    twin.close()
    assert k_cl > n_id + 40
    again = DigitalTwin(plant(), cfg, history=store, background=False)  # no backlog now
    run = again.run(progress=False)
    again.close()
    assert run.resume["resumed"] and run.k_closed_loop == k_cl
