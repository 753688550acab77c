"""A live plant's twin built without stalling the sample loop (issue #11).

The oracles: of the model, the synchronous identification of the same samples
(:func:`identify_initial`); of the first controller, the optimizer's tuning called here at
the same operating point; of the inputs, the seeded continuation of the excitation
(:func:`continued_excitation`).  The fit is held back by a gate and the test waits for the
worker before each sample, so that the sample at which the twin is born does not depend on
the machine's speed.
"""

from __future__ import annotations

import math
import threading

import numpy as np
import pytest

import kautztwin as kt
from kautztwin.twin.digital import discretize_model
from kautztwin.twin.runtime import birth


class _LivePlant:
    """A live plant (the loop pairs samples with the inputs it reports applied)."""

    connected = True

    def __init__(self, plant) -> None:
        self.p, self.dt, self.name = plant, plant.dt, plant.name
        self.input_limits = plant.input_limits

    def reset(self):
        self.applied: list[float] = []
        return self.p.reset()

    def step(self, u):
        self.applied.append(float(u))
        r = self.p.step(u)
        return kt.twin.Reading(r.t, r.y, {**r.meta, "u_applied": float(u), "queued": 0})

    def close(self) -> None:
        self.p.close()


def _plant():
    from kautztwin.twin import HydraulicPlant

    return _LivePlant(HydraulicPlant(dt=0.02, temperature=20.0, noise=0.01, random_state=1))


def _config():
    from kautztwin.twin.runtime import TwinConfig

    return TwinConfig.for_plant("hydraulic", duration=12.0, quick=True, static_twin=False)


@pytest.fixture
def gate(monkeypatch):
    """Hold the background fit until the test opens the gate."""
    opened = threading.Event()
    real = birth.identify_initial

    def gated(*args):
        assert opened.wait(60), "the test never opened the gate"
        return real(*args)

    monkeypatch.setattr(birth, "identify_initial", gated)
    return opened


def _until_born(twin, gate, wait: int) -> tuple[int, int]:
    """Step ``wait`` samples past ``n_ident`` with the fit held back, then to the twin's birth.

    Returns the sample at which the fit arrived and the birth sample.
    """
    n_id = twin.config.n_ident
    while twin.k < n_id + wait:
        twin.step()
        assert twin.updater is None  # still identifying: no twin, no controller
    gate.set()
    assert twin._birth.wait(60)
    k_fit = twin.k
    while twin.updater is None:
        twin._birth.wait(60)  # the tuning: submitted with the twins
        twin.step()
    return k_fit, twin.k - 1


def _tuned_here(cfg, model, point):
    """The oracle of the first controller's tuning: the optimizer called in this process."""
    from kautztwin.twin.optimization import Optimizer

    return Optimizer().tune_controller(model, cfg.mpc, step=cfg.tuning_step(), u_op=point[0],
                                       y_op=point[1])


def _candidates(tuning) -> list:
    return [(c["r"], c["score"], c["valid"]) for c in tuning.payload()["candidates"]]


def test_live_twin_keeps_exciting_the_plant_while_it_is_built(gate):
    from kautztwin.twin.report import compute_metrics
    from kautztwin.twin.runtime import DigitalTwin
    from kautztwin.twin.runtime.excitation import continued_excitation
    from kautztwin.twin.runtime.twins import identify_initial

    cfg = _config()
    n_id, wait = cfg.n_ident, 40
    twin = DigitalTwin(_plant(), cfg, background=True)
    twin.start()
    k_fit, k_born = _until_born(twin, gate, wait)
    first = twin.controller.settings
    run = twin.run(progress=False)
    twin.close()
    a = run.arrays
    # the plant got the excitation's continuation until the twin was born: no input held
    more = continued_excitation(cfg)
    np.testing.assert_array_equal(a["u"][n_id:k_born], more[:k_born - n_id])
    assert set(np.round(a["u"][n_id:k_born] - cfg.ident_level, 12)) == {
        -cfg.ident_amplitude, cfg.ident_amplitude}
    # the twins stepped through every sample before the birth, a slice per sample
    assert np.all(np.isfinite(a["y_pred"][1:k_born]))
    assert k_born - k_fit == math.ceil((k_fit - birth.CATCH_UP_SLICE) / (birth.CATCH_UP_SLICE - 1))
    # the model is the synchronous identification of the first n_ident samples, exactly
    sync = identify_initial(cfg, a["u"][:n_id].copy(), a["y_clean"][:n_id].copy())
    ident = run.identification
    assert ident["n_samples"] == n_id and ident["k_twin"] == k_born
    assert ident["fit_percent"] == sync.fit_percent
    assert ident["poles"] == [[float(p.real), float(p.imag)] for p in sync.model.poles]
    # the first controller was tuned at the centre and the output the fit arrived at
    point = (cfg.ident_level, float(a["y_clean"][k_fit - 1]))
    assert ident["tuning_point"] == list(point)
    here = _tuned_here(cfg, discretize_model(sync.model, cfg.dt), point)
    assert first == here.settings and run.tunings[0]["r"] == here.settings.r
    # no controller before the twin; the closed loop after it, within the limits
    assert np.all(np.isnan(a["mpc_ms"][:k_born])) and run.k_closed_loop >= k_born
    assert np.isfinite(a["mpc_ms"][run.k_closed_loop])
    assert compute_metrics(run)["constraint_violations"] == 0


def test_resumed_live_run_builds_its_twin_where_the_stored_run_did(gate, tmp_path):
    from kautztwin.twin.runtime import DigitalTwin

    cfg = _config()
    store = tmp_path / "h.sqlite"
    twin = DigitalTwin(_plant(), cfg, history=store, background=True)
    twin.start()
    _, k_born = _until_born(twin, gate, 25)
    while twin.k < k_born + 150:
        twin.step()
    version, coef = twin.state.version, twin.updater.estimator_.coef_.copy()
    settings = twin.controller.settings
    point = twin.result().identification["tuning_point"]
    twin.finish()
    twin.close()
    again = DigitalTwin(_plant(), cfg, history=store, background=True)
    state = again.start()
    try:
        assert state.replayed and again.k == k_born + 150
        assert again._birth is None  # the stored run's twin: nothing built in the background
        ident = again.result().identification
        assert ident["k_twin"] == k_born and ident["tuning_point"] == point
        assert state.version == version and again.controller.settings == settings
        np.testing.assert_allclose(again.updater.estimator_.coef_, coef, rtol=0, atol=1e-12)
    finally:
        again.close()


def test_process_worker_gives_the_synchronous_fit_and_tuning_bit_for_bit():
    from kautztwin.twin.optimization import Optimizer
    from kautztwin.twin.runtime.twins import identify_initial, make_twins

    cfg = _config()
    rng = np.random.default_rng(3)
    plant = _plant()
    plant.reset()
    u = cfg.ident_level + cfg.ident_amplitude * np.sign(rng.standard_normal(cfg.n_ident))
    y = np.array([plant.step(v).y for v in u])
    sync = identify_initial(cfg, u, y)
    bg = birth.BackgroundBirth(cfg, "process")
    try:
        bg.submit(u, y)
        assert bg.wait(120) and bg.fit_due(0)
        fit = bg.take_fit()
        twins = make_twins(fit, cfg, background=False)
        point = (cfg.ident_level, float(y[-1]))
        bg.conceive(fit, twins, Optimizer(), point)
        assert bg.wait(120)
        ready, tuning = bg.tuning()
    finally:
        bg.close()
    assert fit.fit_percent == sync.fit_percent and fit.offset == sync.offset
    np.testing.assert_array_equal(fit.model.coefficients, sync.model.coefficients)
    np.testing.assert_array_equal(fit.model.basis.poles, sync.model.basis.poles)
    here = _tuned_here(cfg, twins[0].digital_model.model, point)
    assert ready and tuning.settings == here.settings
    assert _candidates(tuning) == _candidates(here)


def test_a_failed_identification_is_the_runs_error(monkeypatch):
    from kautztwin.twin.runtime import DigitalTwin, TwinError

    def fails(*args):
        raise TwinError("the initial identification failed: no data")

    monkeypatch.setattr(birth, "identify_initial", fails)
    twin = DigitalTwin(_plant(), _config(), background=True)
    twin.start()
    try:
        with pytest.raises(TwinError, match="initial identification failed"):
            while twin.k < 3 * twin.config.n_ident:
                twin.step()
    finally:
        twin.close()
