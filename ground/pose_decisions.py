"""The pose correction's decisions: whether what it fitted is applied. A correction must explain the structure (the
floor and walls on their planes to within the noise: `matters`, `plane_brought_on`), bring a floor the walls confirm
onto z = 0 by more than its sightings' scatter (`floor_brought_on`, with `floor_is_level` and `level_clear`), or
bring the pile seen at different times together (`crossings_brought_together`); a registration must stay a drift the
model allows (`is_drift`). Pure functions of residuals and noise levels, tested on their own."""

from __future__ import annotations

import math

import numpy as np
from scipy.special import gammaincinv

from ground.group_stats import group_median, median_sd_m, robust_rms
from ground.pose_knots import DRIFT_LEVEL, MAX_MISFIT, MIN_CELL_POINTS, MIN_VOTES, PLANE_NAMES
from ground.uncertainty import SharedDraws


def plane_brought_on(r_before: np.ndarray, r_after: np.ndarray, plane: np.ndarray, noise_m: float) -> str | None:
    """The first wall (its name) whose points a correction brings onto it: their robust RMS distance comes down
    to within MAX_MISFIT noise levels (as a drift the model explains leaves them), and by more than the noise and
    more than what is left (the correction explains most of the plane's mean square: a drift larger than the
    plane's own scatter). None when no wall's does. r_before, r_after: the same points' distances before and
    after; plane: each one's.

    Why a plane of its own, beside all the points together: the floor's points out-number the walls', and the
    floor does not see a horizontal drift (a loop whose logged position drifts 0.5 m along x alone left all the
    points' robust RMS 0.39 -> 0.36 cm against 0.29 cm of noise). Why "onto": a plane whose points are off it
    either way has not been brought onto it by the correction (a pile's toe on the floor's plane, 21.8 -> 10.6 cm
    against 1.3 cm of noise, on an error-free flight). Why "more than what is left": the data's noise comes from
    neighbouring samples, and a wall seen far off scatters more than it says (error-free flights with the
    datasheet's noise: a wall's points 24.2 -> 22.9 cm against 7.8 cm of noise, another's 16.4 -> 13.5 cm against
    5.3 cm, each moved 4-9 cm by a correction fitted to that scatter). Why the walls only: the floor's points may
    be a pile's flat top, which a height correction pulls down onto the floor's plane (error-free flights over an
    irregular pile with Appendix A's noise: 570 points 109 -> 14 cm, the height moved 0.9 m, Ve -2.3 -> -44.8 %);
    the height has its own tests, and the floor sees no horizontal drift, the blind spot this closes."""
    for j, name in enumerate(PLANE_NAMES):
        m = plane == j
        if name == "floor" or np.count_nonzero(m) < MIN_VOTES:
            continue
        before, after = robust_rms(r_before[m]), robust_rms(r_after[m])
        if after <= MAX_MISFIT * noise_m and before ** 2 - after ** 2 > max(noise_m, after) ** 2:
            return name
    return None


FLOOR_TREND_P = 0.01
"""A floor taken down onto z = 0 must be level: its sightings' heights may not trend with their distance from the
walls at this significance (Kendall's tau, two-sided) by more than MAX_MISFIT noise levels (`floor_is_level`)."""


def floor_is_level(height_m: np.ndarray, wall_distance_m: np.ndarray, noise_m: float) -> bool:
    """Whether a floor's sightings (their heights and distances from the nearest wall) show no trend with the
    distance from the walls: none significant (Kendall's tau at FLOOR_TREND_P), or one that moves them by no more
    than MAX_MISFIT of a point's noise (noise_m) over the distances seen (Theil-Sen's slope over their 5th-95th
    percentiles). A floor is level, while a pile's flank that the vote took for floor rises away from the walls it
    meets at zero height (an irregular pile under Appendix A's noise: tau +0.32 to +0.49, p 1e-7 to 3e-4; 1.25 m over
    the distances seen against 0.37 m), or towards a wall it is heaped against. Real floors under the same noise:
    |tau| <= 0.17, p >= 0.011; without noise a floor's sightings show a trend of 0.1 mm/m that is significant and
    immaterial (0.1 cm over 15 m against 0.9 cm)."""
    if len(height_m) < MIN_VOTES:
        return False
    from scipy.stats import kendalltau, theilslopes  # here: scipy.stats costs every command a quarter second to load
    if not kendalltau(wall_distance_m, height_m).pvalue < FLOOR_TREND_P:
        return True
    lo, hi = np.percentile(wall_distance_m, [5.0, 95.0])
    return abs(float(theilslopes(height_m, wall_distance_m).slope)) * (hi - lo) <= MAX_MISFIT * noise_m


def level_clear(height_m: np.ndarray, shared_sd_m: float, n_significant: float) -> bool:
    """Whether sightings' median height lies off z = 0 by more than n_significant of its standard error: a median's
    of their own scatter (1.25 robust sd / sqrt(n)) and the pose draws they share (shared_sd_m), in quadrature.

    Why the shared draws: a pose message's position error moves every point it places alike, so sightings made in
    the same few messages are off together, and their own scatter does not show it. The paper's pile 2 under Appendix
    A's noise shows its floor for one second at the start (116 points in 17 messages of 0.11 m): it read 0.12 m above
    z = 0 on an error-free flight, and taken down onto it the volume read 4.4 pp low (docs/design-notes.md)."""
    h = np.asarray(height_m, dtype=float)
    if not len(h):
        return False
    level = float(np.median(h))
    own = 1.25 * robust_rms(h - level) / math.sqrt(len(h))
    return abs(level) > n_significant * math.hypot(own, shared_sd_m)


def draw_sd_m(draws: SharedDraws | None, points: np.ndarray) -> float:
    """The standard error the pose draws shared by the points (a mask over draws.group) put on their mean height: one
    draw of draws.sigma_m per pose message among them, as the volume's interval counts them
    (`ground.uncertainty.shared_draws`). 0 without such a draw."""
    if draws is None or not np.any(points):
        return 0.0
    return draws.sigma_m / math.sqrt(len(np.unique(draws.group[points])))


def floor_brought_on(z_before: np.ndarray, z_after: np.ndarray, key: np.ndarray, noise_m: float,
                     most_down_m: float = 0.0, wall_distance_m: np.ndarray | None = None,
                     material_distance_m: np.ndarray | None = None, draws: SharedDraws | None = None,
                     n_significant: float = 3.0, quantum_m: float = 0.0) -> bool:
    """Whether a height correction brings the floor it was solved on onto z = 0 (z_before, z_after: the heights of
    the floor's points before and after it; key: each one's sighting, a knot interval and cell): its sightings (each
    one's median) come onto it by more than their noise and more than what is left (as `plane_brought_on` asks of a
    wall's points), to within MAX_MISFIT noise levels of it or MAX_MISFIT times closer than before (a wall's points
    have the sensor's noise to reach; the floor's, the height drift model's misfit between knots as well: 1.3 cm
    against an ideal sensor's 0.3 cm, measured on a `flow` flight). Up from below z = 0 always; down from above it
    only by no more than most_down_m (the most the logged reference is believed off) and only when the floor is
    level (`floor_is_level`, on the points' wall_distance_m; without them, never down), its level clear of z = 0
    (`level_clear`, with the pose draws its points share: draws, their messages), and its sightings farthest from the
    material beside it (material_distance_m: the nearer half left out) and, with pose draws, its earlier and its later
    sightings each clear of it as well. Either way the floor must lie more than half the range's quantum (quantum_m)
    off z = 0.

    Why sightings and not points: the points of one sweep share its pose, so their count overstates what they know,
    while their own scatter hides an offset. Under the paper's Appendix A noise (a degree of pointing: 0.12 m a point)
    a floor 5 cm below z = 0 came up onto it by less than a point's noise, and the volume stayed 2.5 % low; a
    sighting's noise is its median's (`median_sd_m`), and the same floor's sightings pass (docs/design-notes.md).

    Why up always, down only so far and only when level: nothing lies below the floor, so a floor seen below z = 0 is
    a height error (a lever arm's z entered too far down, an altitude reference reading low), while a floor seen above
    it may be material covering it. A pile's flat top taken for a floor the walls' feet confirmed (-0.69 m on 3 of 220
    error-free flights, the volume about 20 % low; 0.82 m up on pile 2 under Appendix A's noise) lies beyond what a
    barometer walks in a flight; an irregular pile's flanks rising from its walls, 0.39 m up on average and within
    it, passed every other test (one of 648 error-free runs with Appendix A's noise, Ve +0.1 -> -19 %), but not a
    level floor's (docs/design-notes.md). Why the far half: under a degree of pointing noise a floor patch beside a
    pile's toe reads high, the toe's hits placed on the floor beside it (pile 1 of the paper at P_traj 30 %, an
    error-free flight: the floor's sightings 0.16 m up nearest the pile, 0.02 m in the far half; taken down, the
    volume read 1.3 pp low), while a height offset lifts the far half as much as the near. Why early and late: an
    offset of the flight's shows all flight long, while a floor seen in one moment reads that moment's errors. Why
    half the quantum: the ranges are rounded to it, and a floor seen by a few sweeps at nearly one range shares its
    rounding error, which no count of sightings averages out (the paper's pile 1 at P_traj 20 % without noise: a floor
    2.8 mm below z = 0 under a 1 cm quantum, brought up on 3 of 20 servo phases, the volume 0.02-0.10 pp further
    from the truth)."""
    if len(z_before) < MIN_VOTES:
        return False
    when = z_before if draws is None else draws.group.astype(float)
    uniq, g_before, mad, message, count = group_median(key, z_before, when)
    _, g_after, _, _, _ = group_median(key, z_after, z_after)
    many = count >= MIN_CELL_POINTS
    if np.count_nonzero(many) < MIN_VOTES:
        return False
    g_before, g_after, uniq, message = g_before[many], g_after[many], uniq[many], message[many]

    # the sightings with the correction's changes over the flight applied and not its constant part: a drift of the
    # height is taken out, the floor's offset from z = 0 left, which its level tests then judge
    steady = g_after - float(np.median(g_after - g_before))

    def clear(kept: np.ndarray) -> bool:
        """Whether the sightings kept lie above z = 0 on their own (`level_clear`)."""
        return float(np.median(steady[kept])) > 0.0 and level_clear(
            steady[kept], draw_sd_m(draws, np.isin(key, uniq[kept])), n_significant)
    sd = float(np.median(median_sd_m(mad[many], count[many], noise_m)))
    before, after = robust_rms(g_before), robust_rms(g_after)
    level, moved = float(np.median(g_before)), float(np.median(g_after - g_before))
    if not (after <= max(MAX_MISFIT * sd, before / MAX_MISFIT) and before ** 2 - after ** 2 > max(sd, after) ** 2):
        return False
    if abs(level) <= quantum_m / 2.0:
        return False
    if level < 0.0 < moved:
        return True
    if not (moved < 0.0 < level and -moved <= most_down_m and wall_distance_m is not None):
        return False
    if not clear(np.ones(len(g_before), dtype=bool)):
        return False
    _, distance, _, _, _ = group_median(key, wall_distance_m, wall_distance_m)
    if not floor_is_level(g_after, distance[many], noise_m):
        return False
    late = message > np.median(message)
    if draws is not None and not all(part.any() and clear(part) for part in (late, ~late)):
        return False
    if material_distance_m is None:
        return True
    _, near, _, _, _ = group_median(key, material_distance_m, material_distance_m)
    return clear(near[many] >= np.median(near[many]))


def crossings_brought_together(before_m: float, after_m: float, noise_m: float) -> bool:
    """Whether a height correction matters to the pile seen at different times (`crossings_misfit_m` before and after
    it, and the noise of its sightings): they come together by more than their noise and by more than what is left,
    as `plane_brought_on` asks of a wall's points. A height off by a constant moves every sighting alike and never
    passes: that is the floor's question (`floor_brought_on`)."""
    return before_m ** 2 - after_m ** 2 > max(noise_m, after_m) ** 2


def matters(r_before: np.ndarray, r_after_fit: np.ndarray, r_after: np.ndarray, plane: np.ndarray,
            noise_m: float) -> bool:
    """Whether a correction matters to the floor and walls: all their points together come closer to their planes
    by more than the noise (robust RMS of r_before against that of r_after_fit, the points on a plane after the
    fit), or one wall's are brought onto it (`plane_brought_on`, on the same points' r_before and r_after)."""
    return (robust_rms(r_before) ** 2 - robust_rms(r_after_fit) ** 2 > noise_m ** 2
            or plane_brought_on(r_before, r_after, plane, noise_m) is not None)


def capped_gain(before_m: np.ndarray, after_m: np.ndarray, noise_m: float, cap: float) -> float:
    """The chi-square a correction gains on points (their distances before and after, in units of the noise, squared),
    each point's term capped at cap: a point far off its plane (the pile beside it) cannot carry the test."""
    return float(np.sum(np.minimum((before_m / noise_m) ** 2, cap) - np.minimum((after_m / noise_m) ** 2, cap)))


def chi2_quantile(level: float, dof: int) -> float:
    """Chi-square's quantile, as scipy.stats computes it (2 P^-1(dof/2, level)), from scipy.special: importing
    scipy.stats added a quarter of a second to every `pilescan-ground` start."""
    return 2.0 * float(gammaincinv(dof / 2, level))


def drift_steps_chi2(x: np.ndarray, step: np.ndarray, comps: tuple[int, ...]) -> tuple[float, int]:
    """The sum of squares of the knot-to-knot steps of x's (K, 4) components `comps`, in the drift model's step
    sigmas (`prior_sigmas`), and how many steps that is."""
    c = list(comps)
    if len(x) < 2 or not c:
        return 0.0, 0
    d = np.diff(x[:, c], axis=0) / step[c]
    return float(np.sum(d * d)), int(d.size)


def is_drift(x_new: np.ndarray, x_old: np.ndarray, step: np.ndarray, comps: tuple[int, ...],
             level: float = DRIFT_LEVEL) -> bool:
    """Whether x_new is x_old plus a drift the model allows: its steps' norm (in step sigmas) within x_old's plus
    the norm a drift reaches at chi-square's `level` (the triangle inequality: the walls' fit has steps of its
    own, from its own noise, which the registration may smooth or keep, and it may add a drift's worth).

    The pile seen twice observes a shift only through its slope (`register_from_crossings`), linearised about
    the current points; where the cells seen twice are nearly flat (the floor by home, where a flight starts and
    ends hovering), millimetres between passes read as metres of shift. Measured: a VIO flight of a ridge
    registered 3.1 and 6.0 m of along-track shift in its last two knots (0.2 m true) against a step sigma of
    0.12 m: a sum of squares of 1,273 over 60 steps, against the walls' fit's 1.1 and chi-square's 99 % quantile
    of 88; the registrations that helped on the paper's piles summed 57-193 over 128-132 steps, with the walls'
    fit at 21-243."""
    s_new, n = drift_steps_chi2(x_new, step, comps)
    if n == 0:
        return True
    s_old = drift_steps_chi2(x_old, step, comps)[0]
    return math.sqrt(s_new) <= math.sqrt(s_old) + math.sqrt(chi2_quantile(level, n))


def explains_more(structure_m: tuple[float, float], structure_noise_m: float, crossings_m: tuple[float, float],
                  crossings_noise_m: float) -> bool:
    """Whether the second of two corrections of one flight explains it better than the first: the floor and walls'
    robust RMS off their planes (structure_m: first, second) and the pile seen at different times' disagreement with
    itself (crossings_m, `ground.pose_height.crossings_misfit_m`), each squared in its own noise (a reduced
    chi-square of each kind of evidence) and added. The two kinds see different mounting errors: the floor and walls
    a servo's offset and scale and the LiDAR's tilt; the pile seen on passes flown in opposite directions a sweep
    plane yawed off square, which moves each side's points along the track the other way and which the walls beside
    the track do not see. Equal weights: neither is the other's better judge."""
    def score(i: int) -> float:
        return (structure_m[i] / structure_noise_m) ** 2 + (crossings_m[i] / crossings_noise_m) ** 2
    if not (structure_noise_m > 0 and crossings_noise_m > 0):
        return False
    return score(1) < score(0)
