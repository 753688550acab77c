"""A session of step tests at rising oil temperature (the paper's 30 x 900 records)."""

from __future__ import annotations

import numpy as np

from ..._validation import (
    check_finite,
    check_int,
    check_memory,
    check_number,
)
from ...exceptions import DataError
from .drive import HydraulicServoDrive
from .parameters import DEFAULT_T_END, NOMINAL_COMMAND, HydraulicParameters, _check_temperature
from .results import StepTestRecords

__all__ = ["simulate_step_tests", "step_tests_nbytes"]


def step_tests_nbytes(n_records: int, n_samples: int) -> float:
    """Bytes the arrays of :func:`simulate_step_tests` take: ``u``, ``y``, ``y_true`` and ``t``.

    Parameters
    ----------
    n_records, n_samples : int

    Returns
    -------
    float
        ``8 * (3 * n_records * n_samples + n_samples)`` (a float, so it cannot overflow).
    """
    return 8.0 * (3.0 * float(n_records) * float(n_samples) + float(n_samples))


# --------------------------------------------------------------------------- step tests
def simulate_step_tests(
    n_records: int = 30,
    n_samples: int = 900,
    temperatures: tuple[float, float] = (20.0, 60.0),
    *,
    t_end: float = DEFAULT_T_END,
    amplitude: float = NOMINAL_COMMAND,
    noise: float = 0.01,
    random_state: int | np.random.Generator | None = None,
    parameters: HydraulicParameters | None = None,
) -> StepTestRecords:
    """Simulate a session of step tests while the oil warms up (the paper's 30 x 900 data).

    Record ``k`` is a step response from rest at an oil temperature rising
    linearly from ``temperatures[0]`` (first record) to ``temperatures[1]``
    (last record), sampled at ``n_samples`` points on ``[0, t_end]``.

    Parameters
    ----------
    n_records : int, default=30
        Number of step responses (>= 1).
    n_samples : int, default=900
        Samples per response (>= 2).
    temperatures : (float, float), default=(20.0, 60.0)
        Oil temperature of the first and the last record, °C (``lo <= hi``).
    t_end : float, default=3.0
        Record length, s.
    amplitude : float, default=0.5
        Step size of the valve command.
    noise : float, default=0.01
        Sensor-noise standard deviation as a fraction of each record's peak.
    random_state : int, numpy.random.Generator or None, default=None
        Seed of the noise.
    parameters : HydraulicParameters, optional
        Physical parameters; the nominal set when omitted.

    Returns
    -------
    StepTestRecords

    Raises
    ------
    DataError
        On a non-positive count or length, a decreasing or out-of-range
        temperature pair, a zero amplitude or a negative noise level; on records
        that would not fit in memory (checked before anything is simulated), or
        a noise level so large that the records overflow to inf.

    See Also
    --------
    HydraulicServoDrive.step_response : One step response.

    Examples
    --------
    >>> from kautztwin.simulators import simulate_step_tests
    >>> rec = simulate_step_tests(3, 200, (20, 60), random_state=0)
    >>> rec.y.shape, rec.temperature.tolist()
    ((3, 200), [20.0, 40.0, 60.0])
    """
    n_records = check_int(n_records, "n_records")
    if n_records < 1:
        raise DataError(f"n_records must be >= 1, got {n_records}")
    n_samples = check_int(n_samples, "n_samples")
    if n_samples < 2:
        raise DataError(f"n_samples must be >= 2, got {n_samples}")
    try:
        lo, hi = (float(v) for v in temperatures)
    except (TypeError, ValueError):
        raise DataError(
            f"temperatures must be a pair (lo, hi) of numbers in °C, got {temperatures!r}"
        ) from None
    lo = _check_temperature(lo, "temperatures[0]")
    hi = _check_temperature(hi, "temperatures[1]")
    if lo > hi:
        raise DataError(f"temperatures must satisfy lo <= hi, got ({lo:g}, {hi:g})")
    t_end = check_number(t_end, "t_end")
    if t_end <= 0:
        raise DataError(f"t_end must be > 0 s, got {t_end:g}")
    check_memory(
        step_tests_nbytes(n_records, n_samples),
        f"{n_records} records x {n_samples} samples (u, y, y_true)",
    )
    drive = HydraulicServoDrive(parameters if parameters is not None else HydraulicParameters())
    t = np.linspace(0.0, t_end, n_samples)
    temps = np.linspace(lo, hi, n_records)
    rng = np.random.default_rng(random_state)
    u = np.empty((n_records, n_samples))
    y = np.empty_like(u)
    y_true = np.empty_like(u)
    with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below
        for k, T in enumerate(temps):
            r = drive.step_response(t, amplitude, float(T), noise=noise, random_state=rng)
            u[k], y[k], y_true[k] = r.u, r.y, r.y_true
    try:
        check_finite(y, "the simulated records y")
    except DataError as exc:
        raise DataError(f"{exc}: noise = {noise:g} of the peak overflows; use a smaller noise "
                        "level") from None
    return StepTestRecords(
        t=t, u=u, y=y, y_true=y_true, temperature=temps, amplitude=float(amplitude),
        noise=float(noise), parameters=drive.parameters,
    )
