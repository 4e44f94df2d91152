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
