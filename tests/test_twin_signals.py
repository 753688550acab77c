"""SampleSanitizer: dropouts, outliers and late samples are flagged, cleaned and counted."""

from __future__ import annotations

import math

import numpy as np
import pytest

from kautztwin.exceptions import DataError
from kautztwin.twin import SampleFlag, SampleSanitizer

F = SampleFlag


def _noisy(n: int, seed: int = 0, sigma: float = 0.1) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return 20.0 + sigma * rng.standard_normal(n)


def _feed(s: SampleSanitizer, values, t0: int = 0) -> list:
    return [s.process(v, t=t0 + i) for i, v in enumerate(values)]


def test_clean_signal_passes_unchanged():
    x = _noisy(200)
    s = SampleSanitizer()
    out = _feed(s, x)
    np.testing.assert_array_equal([o.value for o in out], x)
    assert all(o.flags == F.NONE and not o.skipped for o in out)
    assert s.counts["ok"] == s.counts["total"] == 200
    assert sum(s.counts[key] for key in ("dropout", "outlier", "late", "held")) == 0


def test_nan_dropout_holds_last_good_value():
    s = SampleSanitizer()
    _feed(s, [1.0, 2.0])
    out = s.process(math.nan, t=2)
    assert (out.value, out.flags, out.skipped) == (2.0, F.DROPOUT | F.HELD, True)
    assert math.isnan(out.raw)
    assert s.process(3.0, t=3).value == 3.0
    assert (s.counts["dropout"], s.counts["held"], s.counts["ok"]) == (1, 1, 3)


def test_dropout_before_any_good_value_gives_fill_value():
    assert math.isnan(SampleSanitizer().process(math.nan).value)
    assert SampleSanitizer(fill_value=0.0).process(None).value == 0.0


@pytest.mark.parametrize(
    "garbage",
    [math.nan, math.inf, -math.inf, None, "abc", "1.5", b"x", [1.0, 2.0], np.array([]), {},
     object(), 1 + 2j, True, 10**400, np.float32("nan"), np.array([[np.inf]])],
    ids=["nan", "inf", "-inf", "none", "str", "numeric-str", "bytes", "list", "empty-array",
         "dict", "object", "complex", "bool", "huge-int", "float32-nan", "2d-inf"],
)  # fmt: skip
def test_garbage_values_are_dropouts_not_exceptions(garbage):
    s = SampleSanitizer()
    _feed(s, [1.0, 1.5])
    out = s.process(garbage, t=5)
    assert out.flags == F.DROPOUT | F.HELD and out.value == 1.5
    assert s.counts["dropout"] == 1


def test_array_scalar_values_are_accepted():
    s = SampleSanitizer()
    assert s.process(np.array([2.5])).value == 2.5
    assert s.process(np.float32(1.5)).value == 1.5
    assert s.process(np.int64(3)).value == 3.0


def test_spike_is_clipped_to_bound():
    x = _noisy(60, seed=1)
    s = SampleSanitizer(window=25)
    assert all(o.flags == F.NONE for o in _feed(s, x))
    w = x[-25:]
    med = np.median(w)
    scale = 1.482602218505602 * np.median(np.abs(w - med))
    out = s.process(1e3, t=60)
    assert out.flags == F.OUTLIER | F.CLIPPED and not out.skipped
    np.testing.assert_allclose(out.value, med + 5.0 * scale, rtol=1e-12)
    out = s.process(-1e3, t=61)  # the spike did not enter the window
    np.testing.assert_allclose(out.value, med - 5.0 * scale, rtol=1e-12)
    assert (s.counts["outlier"], s.counts["clipped"]) == (2, 2)


def test_spike_is_skipped_when_configured():
    x = _noisy(40, seed=2)
    s = SampleSanitizer(outlier_action="skip")
    _feed(s, x)
    out = s.process(500.0, t=40)
    assert (out.value, out.flags, out.raw) == (x[-1], F.OUTLIER | F.HELD, 500.0)
    assert (s.counts["outlier"], s.counts["held"], s.counts["clipped"]) == (1, 1, 0)


def test_spikes_in_noisy_signal_are_all_caught():
    x = _noisy(500, seed=3)
    spikes = np.arange(30, 500, 37)
    x[spikes] += np.where(spikes % 2 == 0, 50.0, -50.0)
    values, flags = SampleSanitizer().process_many(x, t=np.arange(500.0))
    flagged = np.flatnonzero(flags & F.OUTLIER)
    np.testing.assert_array_equal(flagged, spikes)
    assert np.all(np.abs(values - 20.0) < 1.0)


def test_level_shift_is_accepted_after_max_consecutive():
    x = np.concatenate([_noisy(50, seed=4), _noisy(30, seed=5) + 10.0])
    s = SampleSanitizer(max_consecutive=4)
    values, flags = s.process_many(x)
    assert np.all(flags[50:53] == F.OUTLIER | F.CLIPPED)
    assert np.all(flags[53:] == F.NONE)
    np.testing.assert_array_equal(values[53:], x[53:])
    assert (s.counts["level_shift"], s.counts["outlier"]) == (1, 3)


def test_constant_window_flags_nothing_without_min_scale():
    s = SampleSanitizer()
    _feed(s, [0.0] * 30)
    assert s.process(1e-3, t=30).flags == F.NONE
    s = SampleSanitizer(min_scale=1e-4)
    _feed(s, [0.0] * 30)
    assert s.process(1e-3, t=30).flags == F.OUTLIER | F.CLIPPED


@pytest.mark.parametrize(
    "t_late", [4.0, 3.0, math.nan, "yesterday"], ids=["equal", "earlier", "nan", "garbage"]
)
def test_late_sample_is_skipped_and_keeps_last_time(t_late):
    s = SampleSanitizer()
    _feed(s, [1.0, 2.0, 3.0, 4.0, 5.0])
    out = s.process(99.0, t=t_late)
    assert (out.value, out.flags, out.raw) == (5.0, F.LATE | F.HELD, 99.0)
    assert s.last_time == 4.0
    assert s.process(6.0, t=5.0).flags == F.NONE
    assert (s.counts["late"], s.counts["held"], s.counts["gap"]) == (1, 1, 0)


def test_gap_is_flagged_late_but_value_used():
    s = SampleSanitizer(max_gap=1.5)
    _feed(s, [1.0, 2.0])
    out = s.process(3.0, t=4.0)
    assert (out.value, out.flags, out.skipped) == (3.0, F.LATE | F.GAP, False)
    assert (s.counts["late"], s.counts["gap"], s.counts["ok"]) == (1, 1, 2)


def test_dropout_after_gap_keeps_both_flags():
    s = SampleSanitizer(max_gap=1.5)
    _feed(s, [1.0, 2.0])
    assert s.process(math.nan, t=10.0).flags == F.LATE | F.GAP | F.DROPOUT | F.HELD


def test_counts_add_up_on_random_garbage():
    rng = np.random.default_rng(6)
    s = SampleSanitizer(max_gap=2.0)
    pool = [math.nan, None, "x", math.inf, 1e9, -1e9]
    t = 0.0
    n = 2000
    for _ in range(n):
        r = rng.random()
        value = pool[rng.integers(len(pool))] if r < 0.2 else float(rng.normal())
        t += float(rng.choice([-1.0, 0.0, 1.0, 1.0, 1.0, 3.0]))
        out = s.process(value, t=t)
        assert isinstance(out.flags, SampleFlag)
        assert math.isnan(out.value) or math.isfinite(out.value)
    c = s.counts
    assert c["total"] == n
    assert c["held"] == c["dropout"] + (c["late"] - c["gap"]) + c["outlier"] - c["clipped"]
    # every sample is held, clipped, used clean, or used after a gap
    assert n - c["gap"] <= c["ok"] + c["held"] + c["clipped"] <= n
    assert min(c["dropout"], c["late"], c["gap"], c["outlier"]) > 0


def test_reset_clears_state_and_counts():
    s = SampleSanitizer()
    _feed(s, [1.0, math.nan, 2.0])
    s.reset()
    assert s.counts["total"] == 0 and s.last_time is None and math.isnan(s.last_value)


def test_process_many_checks_lengths():
    with pytest.raises(DataError, match="t has 2 samples but values has 3"):
        SampleSanitizer().process_many([1.0, 2.0, 3.0], t=[0.0, 1.0])


def test_process_many_matches_process():
    x = _noisy(100, seed=7)
    x[[10, 40]] = np.nan
    x[70] = 1e4
    values, flags = SampleSanitizer().process_many(x, t=np.arange(100))
    s = SampleSanitizer()
    out = _feed(s, x)
    np.testing.assert_array_equal(values, [o.value for o in out])
    np.testing.assert_array_equal(flags, [int(o.flags) for o in out])


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"threshold": 0.0}, "threshold must be a positive number"),
        ({"window": 2}, "window must be an integer >= 3"),
        ({"window": 5, "min_samples": 6}, "min_samples must be <= window = 5"),
        ({"outlier_action": "drop"}, "outlier_action must be one of 'clip', 'skip'"),
        ({"min_scale": -1.0}, "min_scale must be a finite number >= 0"),
        ({"max_gap": 0.0}, "max_gap must be a positive number or None"),
        ({"max_consecutive": 0}, "max_consecutive must be an integer >= 1"),
    ],
    ids=["threshold", "window", "min-samples", "action", "min-scale", "max-gap",
         "max-consecutive"],
)  # fmt: skip
def test_invalid_parameters_raise(kwargs, match):
    with pytest.raises(DataError, match=match):
        SampleSanitizer(**kwargs)
