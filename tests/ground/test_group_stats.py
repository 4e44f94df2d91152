"""Medians and spreads per group, vectorised (`ground.group_stats`), and the pose vote's peaks
(`ground.pose_correction._peaks`)."""

import numpy as np

from ground.group_stats import group_median, median_sd_m, medians_by_key, rms, robust_rms, sorted_groups
from ground.pose_correction import MIN_VOTES, PEAK_FRACTION, _peaks


def test_that_sorted_groups_are_what_numpys_unique_says_of_sorted_keys():
    rng = np.random.default_rng(0)
    for _ in range(500):
        key = np.sort(rng.integers(0, rng.integers(1, 50), rng.integers(0, 200)))
        want = np.unique(key, return_index=True, return_counts=True)
        got = sorted_groups(key)
        assert all(np.array_equal(w, g) for w, g in zip(want, got, strict=True))


def test_that_medians_by_key_are_each_groups_median():
    rng = np.random.default_rng(1)
    key = rng.integers(0, 30, 2000)
    z = rng.normal(size=2000)
    uniq, med, count = medians_by_key(key, z)
    assert np.array_equal(uniq, np.unique(key))
    assert np.allclose(med, [np.median(z[key == k]) for k in uniq])
    assert np.array_equal(count, [np.count_nonzero(key == k) for k in uniq])


def test_that_group_median_gives_each_groups_median_robust_spread_mean_time_and_count():
    rng = np.random.default_rng(2)
    key = rng.integers(0, 25, 1500)
    z, t = rng.normal(size=1500), rng.uniform(0.0, 100.0, 1500)
    uniq, med, mad, tm, count = group_median(key, z, t)
    assert np.array_equal(uniq, np.unique(key))
    for k, m, s, mean_t, n in zip(uniq, med, mad, tm, count, strict=True):
        zk = z[key == k]
        assert m == np.median(zk) and n == len(zk)
        assert np.isclose(s, 1.4826 * np.median(np.abs(zk - np.median(zk))))
        assert np.isclose(mean_t, t[key == k].mean())


def test_that_a_medians_sd_shrinks_with_its_count_and_is_never_below_the_noise():
    sd = median_sd_m(np.array([0.01, 0.0, 0.04]), np.array([4, 4, 16]), noise_m=0.02)
    assert np.allclose(sd, [1.25 * 0.02 / 2, 1.25 * 0.02 / 2, 1.25 * 0.04 / 4])


def test_that_the_robust_rms_is_a_normal_scatters_sigma_and_ignores_a_gross_outlier_the_rms_does_not():
    r = np.random.default_rng(4).normal(0.0, 0.05, 4000)
    assert abs(rms(r) - 0.05) < 0.002 and abs(robust_rms(r) - 0.05) < 0.003
    r[0] = 100.0
    assert rms(r) > 1.0 and abs(robust_rms(r) - 0.05) < 0.003
    assert rms(np.zeros(0)) == 0.0 and robust_rms(np.zeros(0)) == 0.0


def _peaks_by_loop(h: np.ndarray) -> list[int]:
    """The rule `_peaks` states, bin by bin: a smoothed local maximum (ties to the left) holding enough points,
    placed on its highest raw bin."""
    sm = np.convolve(h, np.ones(3), mode="same")
    need = max(MIN_VOTES, PEAK_FRACTION * float(sm.max()))
    out = []
    for m in range(len(sm)):
        left = sm[m - 1] if m > 0 else -1.0
        right = sm[m + 1] if m + 1 < len(sm) else -1.0
        if sm[m] >= need and sm[m] >= left and sm[m] > right:
            out.append(int(np.argmax(h[max(m - 1, 0):m + 2]) + max(m - 1, 0)))
    return out


def test_that_the_votes_peaks_follow_their_rule_bin_by_bin():
    rng = np.random.default_rng(2)
    for _ in range(2000):
        h = rng.integers(0, rng.integers(1, 40), rng.integers(3, 60))
        if rng.random() < 0.3:
            h[:] = rng.integers(0, 30)  # a plateau: ties everywhere
        assert _peaks(h) == _peaks_by_loop(h)
    assert _peaks(np.array([0, 0, 30, 0, 0, 12, 0])) == [2, 5]
