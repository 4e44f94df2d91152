"""Is the servo really sweeping? A hobby servo has no position feedback, but the ranges tell.

A fixed beam's range changes only as fast as the vehicle moves it (about the flight speed, a few
m/s at most, apart from jumps at edges). A beam swept at the paper's 5 rad/s changes range at
r·tan(incidence)·5 rad/s: tens of m/s at 12 m for most of the sweep. So, per sweep period, the
median rate of range change over 50 ms steps separates the two by an order of magnitude: below
`MIN_SWEEP_RANGE_RATE_M_S` the servo is stuck (or the beam blocked) and the angles logged for that
period cannot be vouched for. 50 ms steps keep 1 cm quantisation and 2.5 cm noise (~1 m/s) far
below the threshold.

Where the ranges are short the test cannot tell: a beam swept over a floor 0.3 m below (the vehicle on the
ground before take-off, or climbing from it) changes range at well under a metre a second, as a stuck one does.
So, given the logged servo angles, a period is judged only where a working sweep would change range at least
twice the threshold: the median over its samples of r |tan gamma| |d gamma / dt|, the rate of a beam swept over
a level floor under a level vehicle at the logged angles and ranges. At survey ranges that is tens of m/s and
every period is judged as before; on the ground it is a fraction of one, and the samples are not blamed on the
servo (they flagged thousands of a networked flight's samples "servo stuck or slow?").
"""

from __future__ import annotations

import math

import numpy as np

MIN_SWEEP_RANGE_RATE_M_S = 5.0
"""Median |dr/dt| below this over a sweep period: not sweeping (see the module docstring)."""
JUDGE_MARGIN = 2.0
"""A period is judged only where a working sweep's expected rate is at least this many thresholds: so a working
sweep there clears the threshold with room for the floor model's error (module docstring)."""
MAX_FLOOR_ANGLE_RAD = math.radians(80.0)
"""The floor model's largest angle: a beam swept flatter meets a wall or the pile's flank first, not the floor, and
tan(gamma) would grow without bound."""
LAG_S = 0.05
MIN_SAMPLES = 20


def stuck_sweep_mask(t_s: np.ndarray, range_m: np.ndarray, usable: np.ndarray, period_s: float,
                     min_rate_m_s: float = MIN_SWEEP_RANGE_RATE_M_S, lag_s: float = LAG_S,
                     servo_rad: np.ndarray | None = None) -> np.ndarray:
    """True for usable samples in sweep periods whose ranges do not move like a swept beam's.

    Periods with fewer than MIN_SAMPLES usable samples, or spanning less than 3/4 of a period, are
    not judged (False); with the logged servo angles, nor are periods whose ranges are too short for a
    working sweep to show (module docstring).
    """
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(range_m, dtype=float)
    g = None if servo_rad is None else np.asarray(servo_rad, dtype=float)
    ok = np.asarray(usable, dtype=bool) & np.isfinite(t) & np.isfinite(r)
    if g is not None:
        ok &= np.isfinite(g)
    out = np.zeros(len(t), dtype=bool)
    idx = np.flatnonzero(ok)
    if len(idx) < MIN_SAMPLES or not (np.isfinite(period_s) and period_s > 0):
        return out
    tu, ru = t[idx], r[idx]
    # rate over ~lag_s: compare each sample with the first one at least lag_s later
    j = np.searchsorted(tu, tu + lag_s)
    has = j < len(tu)
    rate = np.full(len(tu), np.nan)
    rate[has] = np.abs(ru[j[has]] - ru[has]) / np.maximum(tu[j[has]] - tu[has], 1e-9)
    expected = None
    if g is not None:  # a working sweep's rate at these ranges and angles, over a level floor
        gu = g[idx]
        expected = np.full(len(tu), np.nan)
        turn = np.abs(gu[j[has]] - gu[has]) / np.maximum(tu[j[has]] - tu[has], 1e-9)
        flat = np.clip(gu[has], -MAX_FLOOR_ANGLE_RAD, MAX_FLOOR_ANGLE_RAD)
        expected[has] = ru[has] * np.abs(np.tan(flat)) * turn
    window = np.floor((tu - tu[0]) / period_s).astype(np.int64)
    for w in np.unique(window):
        sel = window == w
        vals = rate[sel]
        vals = vals[np.isfinite(vals)]
        span = tu[sel][-1] - tu[sel][0]
        # Only whole periods are judged: a piece of one can sit in the dwell at a sweep's end, where
        # even a working servo barely moves the beam.
        if expected is not None:
            e = expected[sel]
            e = e[np.isfinite(e)]
            if len(e) < MIN_SAMPLES or np.median(e) < JUDGE_MARGIN * min_rate_m_s:
                continue  # too short a range for a sweep to show: not judged
        if span >= 0.75 * period_s and len(vals) >= MIN_SAMPLES and np.median(vals) < min_rate_m_s:
            out[idx[sel]] = True
    return out
