"""Medians per group, vectorised: a median per cell or per knot interval over tens of thousands of groups, where a
Python loop of `np.median` costs a second a call."""

from __future__ import annotations

import numpy as np


def sorted_group_median(z: np.ndarray, start: np.ndarray, count: np.ndarray) -> np.ndarray:
    """Each group's median, the groups contiguous and each sorted: the middle value, or the middle two's mean
    (as np.median)."""
    return 0.5 * (z[start + (count - 1) // 2] + z[start + count // 2])


def sorted_groups(key: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`np.unique(key, return_index=True, return_counts=True)` of keys already sorted, without sorting them again:
    each distinct key, where its run starts and how long it is."""
    if len(key) == 0:
        return key[:0], np.zeros(0, dtype=np.intp), np.zeros(0, dtype=np.intp)
    start = np.flatnonzero(np.concatenate([[True], key[1:] != key[:-1]]))
    return key[start], start, np.diff(np.append(start, len(key)))


def medians_by_key(key: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per distinct key (sorted): the key, the median of z and the count."""
    order = np.lexsort((z, key))
    uniq, start, count = sorted_groups(key[order])
    return uniq, sorted_group_median(z[order], start, count), count


def group_median(key: np.ndarray, z: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, ...]:
    """Per distinct key: the key, the median and robust spread of z, the mean of t, the count."""
    order = np.lexsort((z, key))
    key, z, t = key[order], z[order], t[order]
    uniq, start, count = sorted_groups(key)
    med = sorted_group_median(z, start, count)
    group = np.repeat(np.arange(len(uniq)), count)
    dev = np.abs(z - med[group])
    mad = 1.4826 * sorted_group_median(dev[np.lexsort((dev, group))], start, count)
    tm = np.add.reduceat(t, start) / count
    return uniq, med, mad, tm, count


def median_sd_m(mad_m: np.ndarray, count: np.ndarray, noise_m: float) -> np.ndarray:
    """The sd of a median of `count` points whose robust spread is mad_m (at least noise_m): one sighting's noise, as
    the pose correction's crossings weigh them and judge them (`ground.pose_correction`)."""
    return 1.25 * np.maximum(mad_m, noise_m) / np.sqrt(count)


def rms(x: np.ndarray) -> float:
    """The root mean square (0 of nothing)."""
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else 0.0


def robust_rms(r: np.ndarray) -> float:
    """The RMS a normal scatter would have, from the median absolute value (1.4826 MAD about zero): what gross
    outliers among residuals leave alone (0 of nothing)."""
    return float(1.4826 * np.median(np.abs(r))) if len(r) else 0.0


JACKKNIFE_BLOCKS = 10
"""A jackknife over time cuts a flight into this many blocks (the rangefinder share's, `ground.rangefinder_height`, and
the servo timing offset's, `ground.plane_stretches.beside_a_servo_delay`): as few as leave its variance estimate
usable (nine degrees of freedom, about ±25 % on the standard error), so that each block is as long as the flight
allows and holds what is shared over a stretch of it: a leg or two, several sweeps of each direction. (Blocks
`ground.rangefinder_height.DRIFT_KNOT_S` long were too short on the longer flights: a rangefinder share 6 of their
errors from the truth.)"""


def jackknife_sd(estimates: np.ndarray) -> float:
    """The delete-one-block jackknife's standard error from the estimates made with each block left out in turn."""
    w = np.asarray(estimates, dtype=float)
    return float(np.sqrt((len(w) - 1) / len(w) * np.sum((w - w.mean()) ** 2)))
