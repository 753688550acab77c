"""Twin plants: one Plant protocol, hydraulic simulator, TCLab emulator, CSV replay, clock."""

from __future__ import annotations

import math
import time
import warnings

import numpy as np
import pytest
import tclab  # noqa: E402,F401 - the [tclab] extra, part of [test]

from kautztwin.exceptions import DataError, DimensionError
from kautztwin.simulators import HydraulicServoDrive
from kautztwin.twin.physical import (
    Clock,
    HydraulicPlant,
    Plant,
    Reading,
    ReplayExhaustedError,
    ReplayInputWarning,
    ReplayPlant,
    TCLabPlant,
    TemperatureSchedule,
    run_open_loop,
    temperature_for_pole_ratio,
)


def _steps(n: int, seed: int, lo: float, hi: float) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.repeat(rng.uniform(lo, hi, n // 5 + 1), 5)[:n]


@pytest.fixture
def replay_file(tmp_path):
    t = np.arange(8) * 0.5
    u = np.array([1.0, 1.0, 0.0, 0.0, 2.0, 2.0, 2.0, 2.0])
    y = np.array([0.0, 0.4, 0.7, np.nan, 0.5, 1.1, 1.6, 1.9])  # a recorded dropout
    path = tmp_path / "run.csv"
    np.savetxt(path, np.column_stack([t, u, y]), delimiter=",", header="t,u,y", comments="")
    return path, t, u, y


@pytest.fixture
def plants(replay_file):
    made = [
        HydraulicPlant(dt=0.05),
        TCLabPlant(dt=1.0, random_state=0),
        ReplayPlant.from_csv(replay_file[0]),
    ]
    yield made
    for p in made:
        p.close()


# --------------------------------------------------------------------------- protocol
def test_every_plant_satisfies_the_protocol(plants):
    for plant in plants:
        assert isinstance(plant, Plant), type(plant).__name__
        assert plant.dt > 0 and isinstance(plant.name, str)
        lo, hi = plant.input_limits
        assert lo < hi


def test_reset_and_step_return_readings_on_the_sampling_grid(plants):
    for plant in plants:
        r0 = plant.reset()
        r1 = plant.step(0.5 * sum(plant.input_limits) if plant.name != "run" else None)
        assert isinstance(r0, Reading) and isinstance(r1, Reading)
        assert r1.t == pytest.approx(r0.t + plant.dt)
        assert math.isnan(r0.meta["u"]) and r1.meta["k"] == 1
        with pytest.raises(TypeError):
            r1.meta["u"] = 0.0  # read-only


def test_plants_reject_non_finite_inputs():
    plant = HydraulicPlant(dt=0.05)
    with pytest.raises(DataError, match="finite"):
        plant.step(math.nan)
    with pytest.raises(DataError, match="number"):
        plant.step("open")


# --------------------------------------------------------------------------- hydraulic
def test_hydraulic_stepping_equals_one_long_simulation():
    drive = HydraulicServoDrive()
    schedule = TemperatureSchedule.steps([1.0], [30.0, 50.0], ramp_time=1.0)
    plant = HydraulicPlant(drive, dt=0.02, temperature=schedule, initial_command=0.5)
    u = _steps(150, seed=1, lo=0.3, hi=0.7)
    run = run_open_loop(plant, u)
    t = np.arange(u.size + 1) * 0.02
    long = drive.simulate(
        t, np.append(u, u[-1]), schedule, x0=drive.equilibrium(0.5, schedule(0.0))
    )
    np.testing.assert_allclose(run.t, t, rtol=0, atol=1e-12)
    np.testing.assert_allclose(run.y, long.y_true, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(run.meta("temperature"), long.temperature, rtol=0, atol=1e-12)


def test_hydraulic_noise_is_reproducible_and_reset_restarts():
    plant = HydraulicPlant(dt=0.02, noise=0.5, random_state=3)
    u = np.full(20, 0.6)
    a = run_open_loop(plant, u)
    b = run_open_loop(plant, u)
    np.testing.assert_array_equal(a.y, b.y)
    noise = a.y - a.meta("y_true")
    assert 0.2 < noise.std() < 1.0


def test_hydraulic_input_is_clipped_to_the_stroke():
    plant = HydraulicPlant(dt=0.02)
    assert plant.step(3.0).meta["u"] == 1.0


@pytest.mark.parametrize("drift", [0.4, -0.2], ids=["slower-40pct", "faster-20pct"])
def test_pole_drift_moves_the_dominant_pole_by_the_requested_fraction(drift):
    plant = HydraulicPlant.with_pole_drift(drift, events=(10.0, 20.0), ramp_time=1.0, dt=0.05)
    p0, p_end = plant.dominant_pole(0.0), plant.dominant_pole(30.0)
    assert p_end / p0 == pytest.approx(1.0 - drift, rel=1e-4)
    assert plant.drift_events == (10.0, 20.0)
    mid = plant.dominant_pole(15.0)
    assert mid / p0 == pytest.approx(1.0 - drift / 2, rel=1e-4)


def test_unreachable_pole_ratio_is_an_error():
    with pytest.raises(DataError, match="not reachable"):
        temperature_for_pole_ratio(0.05)


def test_temperature_schedule_checks_its_input():
    with pytest.raises(DataError, match="non-decreasing"):
        TemperatureSchedule([0.0, 2.0, 1.0], [20.0, 30.0, 40.0])
    with pytest.raises(DataError, match="lie in"):
        TemperatureSchedule.constant(500.0)
    with pytest.raises(DimensionError, match="len"):
        TemperatureSchedule.steps([1.0, 2.0], [20.0, 30.0])
    s = TemperatureSchedule.ramp(1.0, 3.0, 20.0, 40.0)
    assert s.constant_between(0.0, 1.0) and not s.constant_between(0.5, 1.5)


# --------------------------------------------------------------------------- clock
def test_fast_clock_never_sleeps_and_real_time_clock_paces():
    fast = HydraulicPlant(dt=0.05)
    start = time.perf_counter()
    for _ in range(10):
        fast.step(0.5)
    fast_elapsed = time.perf_counter() - start

    paced = HydraulicPlant(dt=0.05, clock=Clock.real_time(speedup=5.0))
    start = time.perf_counter()
    for _ in range(10):
        paced.step(0.5)
    elapsed = time.perf_counter() - start
    assert elapsed >= 10 * 0.05 / 5.0 - 1e-3  # 0.1 s of wall-clock time
    assert elapsed > fast_elapsed
    assert paced.clock.now() == pytest.approx(0.5, abs=0.2)


def test_clock_counts_late_ticks():
    clock = Clock.real_time(tolerance=0.0)
    clock.start()
    assert clock.wait_until(-1.0) > 0.9
    assert clock.n_late == 1
    with pytest.raises(DataError, match="speedup"):
        Clock(True, speedup=0.0)


# --------------------------------------------------------------------------- TCLab
def test_tclab_emulator_runs_faster_than_real_time():
    lab = TCLabPlant(dt=1.0, random_state=0)
    start = time.perf_counter()
    run = run_open_loop(lab, np.full(600, 60.0))  # ten minutes of lab time
    wall = time.perf_counter() - start
    lab.close()
    assert run.t[-1] == 600.0
    assert wall < 60.0 / 10  # at least 100 times faster than real time
    assert run.y[-1] > run.y[0] + 15.0  # the heater warmed the thermistor
    assert np.all(np.diff(run.meta("y_true")) >= 0)


def test_tclab_plant_follows_the_tclab_model_exactly():

    lab = TCLabPlant(dt=2.0, noise=0.0)
    u = _steps(50, seed=2, lo=0.0, hi=100.0)
    run = run_open_loop(lab, u)
    lab.close()
    ref = tclab.TCLabModel(synced=False)
    t0 = ref.tlast
    expected = [ref._T1]
    for k, v in enumerate(u):
        ref.Q1(v)
        ref.update(t0 + 2.0 * (k + 1))
        expected.append(ref._T1)
    np.testing.assert_allclose(run.meta("y_true"), expected, rtol=1e-12)
    # readings are quantised like the board's A/D converter
    np.testing.assert_allclose(run.y, [ref.quantize(v) for v in expected], rtol=1e-12)


def test_tclab_emulator_is_reproducible_with_a_seed():
    a = run_open_loop(TCLabPlant(dt=1.0, random_state=5), np.full(30, 80.0)).y
    b = run_open_loop(TCLabPlant(dt=1.0, random_state=5), np.full(30, 80.0)).y
    np.testing.assert_array_equal(a, b)


def test_tclab_heater_is_clipped_and_second_heater_works():
    lab = TCLabPlant(dt=1.0, heater=2)
    assert lab.step(150.0).meta["u"] == 100.0
    lab.close()
    with pytest.raises(DataError, match="heater"):
        TCLabPlant(heater=3)


def test_real_tclab_board_refuses_a_fast_clock():
    with pytest.raises(DataError, match="real time"):
        TCLabPlant(connected=True, clock=Clock())


# --------------------------------------------------------------------------- replay
def test_replay_reproduces_the_file(replay_file):
    path, t, u, y = replay_file
    plant = ReplayPlant.from_csv(path)
    readings = [plant.reset()] + [plant.step(float(v)) for v in u[:-1]]
    np.testing.assert_array_equal([r.t for r in readings], t)
    np.testing.assert_array_equal([r.y for r in readings], y)  # NaN where NaN
    np.testing.assert_array_equal([r.meta["u"] for r in readings[1:]], u[:-1])
    assert plant.dt == 0.5 and plant.input_limits == (0.0, 2.0) and plant.name == "run"
    with pytest.raises(ReplayExhaustedError, match="ends after 8 samples"):
        plant.step(None)


def test_replay_warns_once_when_asked_to_follow_another_input(replay_file):
    plant = ReplayPlant.from_csv(replay_file[0])
    with pytest.warns(ReplayInputWarning, match="cannot follow another input"):
        first = plant.step(5.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        second = plant.step(5.0)  # warned once per run only
    assert (first.y, second.y) == (0.4, 0.7)
    plant.reset()
    with pytest.warns(ReplayInputWarning):
        plant.step(5.0)


def test_replay_follows_the_record_silently_with_none(replay_file):
    plant = ReplayPlant.from_csv(replay_file[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert plant.step(None).meta["u"] == 1.0
    assert plant.remaining == 6


def test_replay_file_errors(tmp_path, replay_file):
    with pytest.raises(DataError, match="no column 'speed'"):
        ReplayPlant.from_csv(replay_file[0], columns=("t", "u", "speed"))
    bad = tmp_path / "bad.csv"
    bad.write_text("t,u,y\n0,1,abc\n")
    with pytest.raises(DataError, match="line 2"):
        ReplayPlant.from_csv(bad)
    with pytest.raises(DataError, match="cannot read"):
        ReplayPlant.from_csv(tmp_path / "missing.csv")
    with pytest.raises(DataError, match="increasing"):
        ReplayPlant([0.0, 0.0, 1.0], [0, 0, 0], [0, 0, 0])
    with pytest.raises(DimensionError, match="one length"):
        ReplayPlant([0.0, 1.0], [0.0], [0.0, 1.0])


def test_replay_in_real_time_keeps_the_recorded_pace():
    plant = ReplayPlant(
        [0.0, 0.05, 0.1], [0, 0, 0], [1.0, 2.0, 3.0], clock=Clock.real_time(speedup=2.0)
    )
    start = time.perf_counter()
    plant.step(None)
    plant.step(None)
    assert time.perf_counter() - start >= 0.05 - 1e-3
