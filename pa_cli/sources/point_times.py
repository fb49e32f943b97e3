"""Per-point time fields: which unit they are in, whether they are absolute, and what they are
relative to.

Drivers store a point's firing time in many ways (docs/sensors.md): seconds relative to a header
stamp at the sweep's start (Ouster `t` in ns) or at its end (Velodyne `time`, negative), absolute
seconds (Hesai, Robosense `timestamp`) or absolute nanoseconds (Livox `timestamp`). Nothing in
the field says which, so the unit and the kind are read from the values:

- unit (`detect_time_unit`): the raw values are in s, ms, us or ns; the unit is the one that makes
  the median sweep span (max - min of a scan's raw times) fall in [max_sweep_s / 1000,
  max_sweep_s). The candidate units are 1000x apart, so exactly one fits; sweeps of 2 ms to 2 s
  are recognised with the default `max_sweep_s` of 2 s.
- kind: absolute when, in that unit, the earliest times lie further than max_sweep_s from 0
  (e.g. UNIX time); relative otherwise.

`sweep_times_s` then counts every point from the scan's earliest point, whatever the field's
origin, so a field relative to a stamp at the sweep's end gives the same times as one relative
to its start.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

TIME_UNITS_S = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9}
UNIT_WINDOW = 1000.0  # ratio between neighbouring candidate units
# Names that suggest a per-point time; a field named so but not read as one is reported, not guessed.
TIME_NAME_HINTS = ("time", "stamp")


@dataclass(frozen=True)
class TimeUnit:
    """How a per-point time field reads: unit name, seconds per raw unit, absolute?"""

    name: str
    seconds_per_unit: float
    absolute: bool


def detect_time_unit(raw_min: np.ndarray, raw_max: np.ndarray, max_sweep_s: float) -> TimeUnit | None:
    """The unit of a per-point time field from each scan's smallest and largest raw time.

    See the module docstring for the rule. Returns None when the times carry no sweep (all
    spans zero or not finite) or no unit puts the median span within one sweep.
    """
    raw_min = np.asarray(raw_min, dtype=np.float64)
    raw_max = np.asarray(raw_max, dtype=np.float64)
    span = raw_max - raw_min
    span = span[np.isfinite(span) & (span > 0)]
    if len(span) == 0:
        return None
    median_span = float(np.median(span))
    for name, scale in TIME_UNITS_S.items():
        span_s = median_span * scale
        if max_sweep_s / UNIT_WINDOW <= span_s < max_sweep_s:
            absolute = bool(np.nanmedian(np.abs(raw_min)) * scale > max_sweep_s)
            return TimeUnit(name, scale, absolute)
    return None


def sweep_times_s(raw_time: np.ndarray, unit: TimeUnit, clock_s: float) -> tuple[np.ndarray, float]:
    """Per-point times (s) from the scan's earliest point, and that point's instant (s).

    `clock_s` is the instant a relative field counts from (a header stamp; ignored for absolute
    fields, whose values are instants themselves). The subtraction is done in the raw unit, so
    integer nanosecond stamps and float64 absolute times keep their precision.
    """
    raw = np.asarray(raw_time)
    start = raw.min()
    origin_s = 0.0 if unit.absolute else clock_s
    return (raw - start).astype(np.float64) * unit.seconds_per_unit, origin_s + float(start) * unit.seconds_per_unit


def looks_like_time(name: str) -> bool:
    """Whether a field's name suggests a per-point time (`t`, or a name holding "time"/"stamp")."""
    lower = name.lower()
    return lower == "t" or any(hint in lower for hint in TIME_NAME_HINTS)
