"""The pose correction's height: from the floor and from the pile seen at different times
(`vertical_from_crossings`, in rounds whose cells' slopes come from the heights corrected so far), the vote's floor
candidates screened across the flight first (`screen_floor`: a flat pile top the vote took for the floor lies above
the floor's level once the crossings align the flight), the level read from below when a pile's toe shows among them,
and what the report says of it: where the height was not tied to a floor, and the level's standard error when no
floor set it. The fits that call these are `ground.pose_correction`'s."""

from __future__ import annotations

import math

import numpy as np
from scipy import sparse
from scipy.sparse.csgraph import connected_components, maximum_flow

from firmware_py.core.storage import Storage
from ground.crossing_cells import cell_slopes, flattened, grid_cells, in_building
from ground.group_stats import group_median, median_sd_m, rms, robust_rms
from ground.huber_lsq import huber_loss, irls_huber, knot_covariance, mean_sigma_m
from ground.plane_stretches import Beams
from ground.pose_knots import (
    BAND,
    MAX_MISFIT,
    MIN_CELL_POINTS,
    MIN_VOTES,
    STRAY_FRACTION,
    corrected_points,
    knot_basis,
    median_spacing_s,
)

SLOPE_ROUNDS = 3
"""Rounds of the height solution, each with the cells' slopes from the previous one's corrected heights (a
slope fitted to uncorrected heights takes up the difference between two passes over a cell)."""


def raised_floor_note(raised_m: float, left_m: float, z_m: np.ndarray, most_down_m: float = math.inf) -> str:
    """The pose line's note on a correction applied because it brought the floor onto z = 0 (`floor_brought_on`):
    by how much (raised_m, on the floor's points: up > 0, down < 0), how far off it they are left (left_m, robust
    RMS), and, when the height correction z_m (the knots') is about the same all flight (its spread under 1/MAX_MISFIT
    of its mean), the two errors that make a constant one. Down, within what (most_down_m): a floor above z = 0 may
    be material covering it, and is believed only within the logged reference's own error."""
    z = np.asarray(z_m, dtype=float)
    even = len(z) > 0 and float(np.std(z)) * MAX_MISFIT < abs(float(np.mean(z)))
    way = "down" if raised_m >= 0.0 else "up"
    cause = (f": a correction this even over the flight is what a lever arm's z entered too far {way}, or an "
             "altitude reference's offset, makes; check the lever arm against the drone") if even else ""
    if raised_m >= 0.0:
        return (f"the height corrected from the floor, which lay {raised_m:.2f} m below z = 0 where nothing but a "
                f"height error puts it (its points now {left_m * 100:.1f} cm off it){cause}")
    within = (f"within the {most_down_m:.2f} m the altitude reference may drift in the flight"
              if math.isfinite(most_down_m) else "the altitude from the downward rangefinder, which only a floor sets")
    return (f"the height corrected from the floor, which lay {-raised_m:.2f} m above z = 0, level and {within} (its "
            f"points now {left_m * 100:.1f} cm off it); were it material covering the floor, the volume would be low "
            f"by as much{cause}")


def level_sigma_m(walk_m_per_sqrt_s: float, duration_s: float) -> float:
    """The standard error of a drifting altitude reference's level over a flight of duration_s: the mean over the
    flight of a random walk (walk_m_per_sqrt_s) that starts at the log's start, whose variance is q^2 T / 3. What the
    height's level is off by when no floor the flight confirmed sets it (`PoseCorrection.level_sigma_m`)."""
    return walk_m_per_sqrt_s * math.sqrt(max(duration_s, 0.0) / 3.0)


def height_again(b: Beams, x: np.ndarray, k: np.ndarray, f: np.ndarray, knots: np.ndarray, wall: np.ndarray,
                 voted: np.ndarray, storage: Storage, cell_m: float, step_z_m: float, noise: float, sensor_m: float,
                 max_error_m: float, n_significant: float, max_vertical_error_m: float,
                 open_shift_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, float | None,
                                             np.ndarray | None, float | None]:
    """The height solved again once the registration has aligned the flight horizontally: the floor screen
    (`_screen`) and the height from the floor and the crossings (`vertical_from_crossings`), as the first
    time, from the logged reference, in the registered frame, with x, y and heading held at the registration's.

    Both were first done in the frame before the registration, which can misplace a stretch of the flight by a
    metre (measured: a `flow` flight over pile 2 whose level was set by 130 points on 0.86 m of pile). Nor is the
    registration's own height kept: it solves the height with the position, and on a pile with a flat top the
    two trade (measured: a `vio` flight over pile 2 at P_traj 5 %, a +0.26 m block of height over 97 s that
    the crossings' misfit prefers by 0.03 cm, 0.17 m RMS of height error; solved again 0.07 m). Returns the
    correction, the height's information, a note, the height's standard error (`height_rounds`; None when the solve
    gave none), the floor it was solved on and, when the walls' feet do not confirm that floor, what anchoring on it
    moved the height (`floor_unconfirmed_note`; None when confirmed); x as it was and None for the rest when the
    registration's height stands (no floor kept, nothing significant, or refused as the first height would be)."""
    x_h = x.copy()
    x_h[:, 2] = 0.0
    p, _ = corrected_points(b, x_h, k, f)
    kept, _, _, _, confirmed = _screen(p, b.t_s, knots, wall, voted, storage, cell_m, step_z_m, noise, sensor_m,
                                       max_error_m)
    if not kept.any():
        return x, None, None, None, None, None
    sigma: list[float] = []
    z, z_info = height_rounds(p, b.t_s, knots, wall, kept, storage, cell_m, step_z_m, noise, max_error_m,
                              n_significant, sigma)
    if (z is None or height_refused(z, knots, step_z_m, n_significant, max_vertical_error_m) is not None
            or floor_unconfirmed_note(z, confirmed, open_shift_m) is not None):
        return x, None, None, None, None, None
    change = rms(z - x[:, 2])
    x_h[:, 2] = z
    return x_h, z_info, (f"the height solved again on the floor once the pile seen at different times aligned the "
                         f"flight ({change * 100:.1f} cm RMS change)"), (sigma[-1] if sigma else None), kept, (
                             None if confirmed else float(np.mean(z)))


def height_rounds(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                  storage: Storage, cell_m: float, step_z_m: float, noise_m: float, max_error_m: float,
                  n_significant: float, sigma_out: list[float] | None = None) -> tuple[np.ndarray | None,
                                                                                     np.ndarray | None]:
    """`vertical_from_crossings` SLOPE_ROUNDS times, each with the cells' slopes from the heights corrected so
    far (`SLOPE_ROUNDS`); (None, None) when a round finds nothing significant. The last round appends its
    height's standard error to sigma_out (`vertical_from_crossings`). When a pile's toe shows among the floor
    candidates (`floor_from_below`), the level is then set where the floor's own candidates lie: the joint solve
    weighs the toe's cells as floor, and measured under Appendix A's noise put the vehicle 4-25 cm low."""
    z = z_info = None
    for i in range(SLOPE_ROUNDS):
        z, z_info = vertical_from_crossings(p, t, knots, wall, floor, storage, cell_m, step_z_m, noise_m,
                                            max_error_m, n_significant, z,
                                            sigma_out=sigma_out if i == SLOPE_ROUNDS - 1 else None)
        if z is None:
            return None, None
    kept = floor_from_below(p, t, knots, z, floor, n_significant)
    if kept is not floor:  # the toe showed: the level is the floor's own, read from the candidates kept
        idx = np.flatnonzero(kept)
        z = z - float(np.median(p[idx, 2] + np.interp(t[idx], knots, z)))
    return z, z_info


REVISIT_INTERVALS = 3
"""Knot intervals between two sightings of a cell for them to be two passes over it: a cell is what the vehicle flies
in a sweep period and a knot interval is two sweep periods, so one pass sees a cell within an interval and the
next; three apart, the vehicle has left and come back."""


MIN_TIE_CELLS = 10
"""Cells that tie a stretch's height to the floor: seen again on other passes, by routes through the flight that share
no cell (`floor_anchored`). A tie fixes one number, the stretch's height against the floor's, and this is ten per
parameter, as MIN_FLOOR_POINTS is for a plane's three. Measured: over the paper's pile 2 at P_traj 5 % the far half
of the loop (33 knot intervals, 98 s) hangs on 5-8 cells of the middle strip seen at 55-62 deg off nadir from both
long legs, and its height came out 4-12 cm off over that stretch (`vio` seeds 0-3). On the pose campaigns' 88
drifting flights, stretches tied by fewer than ten cells: that far half on 5 flights (2 more had it tied by none),
and 9 s stretches of 4 flights over pile 1 at P_traj 5 % (3-9 cells). The truth falls inside the same intervals for
any value from 8 to 20 (37 of the 38 paper-pile flights; docs/design-notes.md, "A height tied by a handful of
cells")."""


def floor_anchored(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                   storage: Storage, cell_m: float, max_error_m: float = math.inf) -> np.ndarray:
    """(K - 1,) per knot interval, whether its height is tied to the floor: the floor seen in it, or MIN_TIE_CELLS
    cells it saw seen again on other passes (`REVISIT_INTERVALS`) in intervals that are tied, by routes through the
    flight that share no cell (the maximum flow from the intervals that saw the floor, each cell seen in two
    intervals a unit of capacity between them). Elsewhere the height rests on a chain, the pile seen from one
    interval to the next, or on a handful of cells, whose errors add up: measured on the paper's pile 2 at P_traj
    5 %, decimetres over 100 s even on the true horizontal pose (docs/design-notes.md). The cells, counts and points
    are `vertical_from_crossings`' (MIN_CELL_POINTS points in a cell and interval, `in_building`)."""
    n_int = len(knots) - 1
    if n_int < 1:
        return np.zeros(0, dtype=bool)
    k, _ = knot_basis(t, knots)
    nx, ny, cid = grid_cells(p, storage, cell_m)
    n_cells = nx * ny
    inside = in_building(p, wall, storage, max_error_m)
    key = k * n_cells + cid
    seen, count = np.unique(key[inside], return_counts=True)
    seen = seen[count >= MIN_CELL_POINTS]
    on_floor, floor_count = np.unique(key[inside & floor], return_counts=True)
    anchor = np.zeros(n_int, dtype=bool)
    anchor[on_floor[floor_count >= MIN_CELL_POINTS] // n_cells] = True
    cell, interval = seen % n_cells, seen // n_cells
    order = np.lexsort((interval, cell))  # by cell, then interval
    cell, interval = cell[order], interval[order]
    src, dst = [], []
    for d in range(1, len(cell)):
        same = cell[d:] == cell[:-d]
        if not same.any():
            break
        revisit = same & (interval[d:] - interval[:-d] >= REVISIT_INTERVALS)
        src.append(interval[:-d][revisit])
        dst.append(interval[d:][revisit])
    i = np.concatenate(src) if src else np.zeros(0, dtype=np.int64)
    j = np.concatenate(dst) if dst else np.zeros(0, dtype=np.int64)
    return _tied_by_cells(anchor, i, j)


def _tied_by_cells(anchor: np.ndarray, i: np.ndarray, j: np.ndarray) -> np.ndarray:
    """Per interval, anchored or joined to the anchored intervals by MIN_TIE_CELLS cells on routes that share none:
    the maximum flow from a source feeding every anchored interval, each cell's revisit (i, j) a unit of capacity
    both ways (a cell seen on many passes links each pair of them). Asked only where an interval's own cells do not
    settle it: the flow to one is at most the cells it shares with any interval, and at least those it shares with
    anchored ones (and 0 outside an anchored interval's component)."""
    n_int = len(anchor)
    links = sparse.coo_matrix((np.ones(len(i), dtype=np.int32), (i, j)), shape=(n_int, n_int)).tocsr()
    links = (links + links.T).tocsr()  # duplicates summed: the cells each pair of intervals shares, both ways
    _, label = connected_components(links, directed=False)
    reached = np.isin(label, label[anchor]) & ~anchor
    degree = np.asarray(links.sum(axis=0)).ravel()
    direct = np.asarray(links[anchor].sum(axis=0)).ravel()
    tied = anchor | (reached & (direct >= MIN_TIE_CELLS))
    ask = np.flatnonzero(reached & (direct < MIN_TIE_CELLS) & (degree >= MIN_TIE_CELLS))
    if len(ask):
        source, feeds = n_int, np.flatnonzero(anchor)
        pairs = links.tocoo()
        net = sparse.csr_matrix((np.concatenate([pairs.data, np.full(len(feeds), np.iinfo(np.int32).max // 4)]),
                                 (np.concatenate([pairs.row, np.full(len(feeds), source)]),
                                  np.concatenate([pairs.col, feeds]))),
                                shape=(n_int + 1, n_int + 1), dtype=np.int32)
        for v in ask:
            tied[v] = maximum_flow(net, source, int(v)).flow_value >= MIN_TIE_CELLS
    return tied


def _untied_runs(tied: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The stretches of REVISIT_INTERVALS knot intervals or more not tied to the floor, as interval ranges [start,
    end): a shorter one lies within a pass's reach of tied intervals on both sides (one interval alone has both its
    knots tied by its neighbours)."""
    free = np.concatenate([[0], (~np.asarray(tied, dtype=bool)).astype(np.int8), [0]])
    edges = np.diff(free)
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    long_enough = ends - starts >= REVISIT_INTERVALS
    return starts[long_enough], ends[long_enough]


def unanchored_stretches(knots: np.ndarray, tied: np.ndarray) -> tuple[float, float, float]:
    """(total s not tied to the floor, the longest such stretch's start and end s) from `floor_anchored`'s
    intervals, counting the stretches `_untied_runs` counts."""
    starts, ends = _untied_runs(tied)
    if len(starts) == 0:
        return 0.0, 0.0, 0.0
    lengths = knots[ends] - knots[starts]
    best = int(np.argmax(lengths))
    return float(lengths.sum()), float(knots[starts[best]]), float(knots[ends[best]])


def untied_sigma_m(knots: np.ndarray, tied: np.ndarray, walk_m_per_sqrt_s: float) -> float:
    """The standard error of the height's mean over the flight from its stretches no floor tied (`_untied_runs` of
    `floor_anchored`'s intervals): there the height rests on the pile seen from one moment to the next, whose links'
    errors add up (decimetres over 100 s, measured), so the data do not check the altitude reference's own drift. A
    stretch of T s between two tied moments is the walk pinned at both ends, a Brownian bridge, whose mean over the
    stretch has variance q^2 T / 12; one open at the flight's start or end is a walk from its tied end, q^2 T / 3 (as
    `level_sigma_m`). Each is weighted by its share of the flight (the legs sweep the floor at a steady rate, so the
    share of the surfaced area whose heights it set), and the stretches, apart in time, add in quadrature. 0 when
    tied throughout."""
    starts, ends = _untied_runs(tied)
    knots = np.asarray(knots, dtype=float)
    flown = float(knots[-1] - knots[0]) if len(knots) >= 2 else 0.0
    if len(starts) == 0 or not flown > 0:
        return 0.0
    n_int = len(knots) - 1
    total = 0.0
    for a, e in zip(starts, ends, strict=True):
        length = float(knots[e] - knots[a])
        pinned_both = a > 0 and e < n_int
        variance = walk_m_per_sqrt_s ** 2 * length / (12.0 if pinned_both else 3.0)
        total += variance * (length / flown) ** 2
    return math.sqrt(total)


def half_sample_mode(x: np.ndarray) -> float:
    """The half-sample mode (Bickel and Fruehwirth, 2006): the shortest half of the values, then the shortest half
    of that, down to two or three. Robust to a one-sided tail, where the median is not."""
    x = np.sort(np.asarray(x, dtype=float))
    if len(x) == 0:
        raise ValueError("the half-sample mode of no values")
    while len(x) > 3:
        h = (len(x) + 1) // 2
        i = int(np.argmin(x[h - 1:] - x[:len(x) - h + 1]))
        x = x[i:i + h]
    if len(x) == 3:
        gap_lo, gap_hi = x[1] - x[0], x[2] - x[1]
        return float(x[1] if gap_lo == gap_hi else np.mean(x[:2]) if gap_lo < gap_hi else np.mean(x[1:]))
    return float(np.mean(x))


def floor_from_below(p: np.ndarray, t: np.ndarray, knots: np.ndarray, z: np.ndarray, floor: np.ndarray,
                     n_significant: float) -> np.ndarray:
    """The floor candidates, with the pile's toe among them dropped when it shows: their heights under the height
    correction z, read from below.

    Nothing lies under the floor but noise, so the candidates below their level show the floor's own scatter; the
    level is their half-sample mode (the floor's peak, not lifted by a toe as a median is). When significantly
    more candidates lie beyond BAND of those sigmas above the level than below it, the excess is a pile's toe
    (under a degree of pointing noise the candidates' band is decimetres tall: measured, 255 of 858 candidates on
    pile 1's toe, 0.24 m up, and every corrected height 4-25 cm low) and only the candidates within BAND sigmas of
    the level are kept. Symmetric tails are left alone: without pointing noise the floor's spread about a solved
    height is the drift model's misfit, and dropping it lost anchors (docs/design-notes.md)."""
    idx = np.flatnonzero(floor)
    if len(idx) < MIN_VOTES:
        return floor
    u = p[idx, 2] + np.interp(t[idx], knots, z)
    level = half_sample_mode(u)
    below = level - u[u < level]
    if len(below) < MIN_CELL_POINTS:
        return floor
    half = BAND * float(np.median(below)) / 0.6745  # the median of a half-normal is 0.6745 sigma
    n_hi, n_lo = int(np.count_nonzero(u > level + half)), int(np.count_nonzero(u < level - half))
    if not n_hi - n_lo > n_significant * math.sqrt(max(n_hi + n_lo, 1)):
        return floor
    keep = np.abs(u - level) <= half
    if not keep.any():
        return floor
    out = floor.copy()
    out[idx[~keep]] = False
    return out


def height_refused(z: np.ndarray, knots: np.ndarray, step_z_m: float, n_significant: float,
                   max_vertical_error_m: float) -> str | None:
    """Why a height correction is not believed (None: it is): it moves the altitude reference further than
    an indoor estimator's is off, or jumps between two knots more than any indoor estimator's does (a flat
    pile top taken for the floor somewhere: the paper's pile 2 hides the floor almost everywhere)."""
    if np.abs(z).max() > max_vertical_error_m:
        return (f"the height was not corrected: the floor seen would put the altitude reference "
                f"{np.abs(z).max():.2f} m off, more than the {max_vertical_error_m:g} m an "
                "indoor estimator's is (a flat pile top taken for the floor?)")
    if len(z) > 1 and np.abs(np.diff(z)).max() > n_significant * step_z_m:
        return (f"the height was not corrected: the floor seen is not consistent (the correction "
                f"would jump {np.abs(np.diff(z)).max():.2f} m between knots {median_spacing_s(knots):.1f} s apart; "
                "a flat pile top taken for the floor?)")
    return None


def vertical_from_crossings(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                            storage: Storage, cell_m: float, step_z_m: float, noise_m: float, max_error_m: float,
                            n_significant: float = 3.0, start: np.ndarray | None = None,
                            significant_only: bool = True,
                            sigma_out: list[float] | None = None,
                            cov_out: list[np.ndarray] | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The height correction at the knots (K,) from the floor and from the pile seen at different times.

    Each knot interval's points in a cell (cell_m: what the vehicle flies in a sweep period, so a cell holds
    both sweep directions' points) give one height, z + c(t); the surface's height there, m, is one unknown
    per cell, the same whenever it is seen; a cell whose points the vote took for the floor (`floor`) has
    m = 0. Solved with the knots' random-walk prior, robustly (Huber: a cell on a slope, whose height
    depends on where in it the points fell, scatters and counts little; a flat part of the pile the vote
    took for the floor is outvoted by the other times that saw it). Returns (None, None) when there is
    nothing to solve or the result is not significant; else the correction and the data's information on
    each knot (1 / m^2). Without floor cells the solution is relative (its level: the prior's zero);
    `significant_only=False` returns it whatever its gain (`screen_floor` needs it). With sigma_out (a list), the
    standard error of the correction's mean over the samples is appended to it when floor cells set the level
    (`mean_sigma_m`)."""
    n_knots = len(knots)
    k, f_t = knot_basis(t, knots)
    seen_z = None if start is None else p[:, 2] + np.interp(t, knots, start)  # slopes from the corrected
    inside, nx, ny, cid, z_flat = flattened(p, wall, storage, cell_m, max_error_m, seen_z)
    key, med, mad, tm, cnt = group_median((k * (nx * ny) + cid)[inside], z_flat[inside], t[inside])
    fkey, _, _, _, fcnt = group_median((k * (nx * ny) + cid)[inside & floor], z_flat[inside & floor],
                                        t[inside & floor])
    is_floor = np.zeros(len(key), dtype=bool)
    pos = np.searchsorted(key, fkey)
    is_floor[pos[fcnt * 2 >= cnt[pos]]] = True  # most of the interval's points in the cell are floor
    keep = cnt >= MIN_CELL_POINTS
    key, med, mad, tm, cnt, is_floor = key[keep], med[keep], mad[keep], tm[keep], cnt[keep], is_floor[keep]
    cell = key % (nx * ny)
    _, inv, times_seen = np.unique(cell, return_inverse=True, return_counts=True)
    floor_cells = np.zeros(times_seen.shape, dtype=bool)
    floor_cells[inv[is_floor]] = True
    use = (times_seen[inv] >= 2) | floor_cells[inv]  # seen once and not floor: says nothing about c
    key, med, mad, tm, cnt, inv = key[use], med[use], mad[use], tm[use], cnt[use], inv[use]
    if len(key) == 0:
        return None, None
    uniq_cells, cell_idx = np.unique(inv, return_inverse=True)
    n_cells = len(uniq_cells)
    fc = np.flatnonzero(floor_cells[uniq_cells])
    rows_s = median_sd_m(mad, cnt, noise_m)
    n_par = n_knots + n_cells
    kk, ff = knot_basis(tm, knots)
    m_obs, m_floor = len(med), len(fc)
    rows = np.concatenate([np.repeat(np.arange(m_obs), 3), m_obs + np.arange(m_floor)])
    cols = np.concatenate([np.column_stack([kk, kk + 1, n_knots + cell_idx]).ravel(), n_knots + fc])
    data = np.concatenate([np.column_stack([(1 - ff) / rows_s, ff / rows_s, -1.0 / rows_s]).ravel(),
                           np.full(m_floor, 1.0 / noise_m)])
    a_obs = sparse.csr_matrix((data, (rows, cols)), shape=(m_obs + m_floor, n_par))
    b_obs = np.concatenate([-med / rows_s, np.zeros(m_floor)])
    # the prior: knot-to-knot steps, a weak pull to zero (the knots) and to the floor (the cells)
    r = n_knots - 1
    steps = np.arange(r)
    pr = np.concatenate([np.repeat(steps, 2), r + np.arange(n_par)])
    pc_ = np.concatenate([np.column_stack([steps, steps + 1]).ravel(), np.arange(n_par)])
    pd = np.concatenate([np.tile([-1.0 / step_z_m, 1.0 / step_z_m], r),
                         np.where(np.arange(n_par) < n_knots, 1.0 / max_error_m, 1.0 / storage.height_m)])
    a_pr = sparse.csr_matrix((pd, (pr, pc_)), shape=(r + n_par, n_par))
    a = sparse.vstack([a_obs, a_pr], format="csr")
    rhs = np.concatenate([b_obs, np.zeros(r + n_par)])
    x = irls_huber(a, rhs)
    info = np.asarray(a_obs[:, :n_knots].multiply(a_obs[:, :n_knots]).sum(axis=0)).ravel()
    # Significance: the heights' misfit with the correction and without it (the cells' heights fitted
    # alone), in the residuals' own spread (a cell on a slope scatters more than its points say), against
    # what fitting the knots to noise would explain.
    r_full = a_obs @ x - b_obs
    a_cells = sparse.vstack([a_obs[:, n_knots:], a_pr[r + n_knots:, n_knots:]], format="csr")
    x_cells = irls_huber(a_cells, np.concatenate([b_obs, np.zeros(n_cells)]))
    r_none = a_obs[:, n_knots:] @ x_cells - b_obs
    spread = max(1.0, robust_rms(r_full))
    gain = 2.0 * float(np.sum(huber_loss(r_none / spread)) - np.sum(huber_loss(r_full / spread)))
    if significant_only and not gain > n_knots + n_significant * math.sqrt(2.0 * n_knots):
        return None, None
    if cov_out is not None:
        cov = knot_covariance(a, x, rhs, n_knots)
        if cov is not None:
            cov_out.append(cov * spread ** 2)
    if sigma_out is not None and m_floor > 0:
        sigma_out.append(mean_sigma_m(a, x, rhs, (k, f_t), n_knots) * spread)
    z = x[:n_knots]
    if m_floor == 0:  # no floor: the level is not observed (the cells' weak pull to 0 would set it): keep the
        z = z - np.mean(z)  # logged reference's on average
    return z, info / spread ** 2


def crossings_misfit_m(p: np.ndarray, t: np.ndarray, knots: np.ndarray, z: np.ndarray, wall: np.ndarray,
                       storage: Storage, cell_m: float, max_error_m: float, noise_m: float) -> tuple[float, float]:
    """How far the pile seen at different times disagrees with itself with the height correction z (K,) at the
    knots: each knot interval's median height in a cell (its slope taken out, as `vertical_from_crossings` does)
    against the cell's median over the intervals that saw it, robust RMS over the cells seen at least twice, m; and
    the noise of those medians (a median's sd, 1.25 of its points' spread, at least noise_m, over the root of their
    count, as `vertical_from_crossings` weighs them): (misfit, noise), (0, 0) when no cell is seen twice."""
    k, _ = knot_basis(t, knots)
    q = np.column_stack([p[:, :2], p[:, 2] + np.interp(t, knots, z)])
    inside, nx, ny, cid, z_flat = flattened(q, wall, storage, cell_m, max_error_m)
    key, med, mad, _, cnt = group_median((k * (nx * ny) + cid)[inside], z_flat[inside], t[inside])
    keep = cnt >= MIN_CELL_POINTS
    cell, med, sd = key[keep] % (nx * ny), med[keep], median_sd_m(mad[keep], cnt[keep], noise_m)
    _, inv, seen = np.unique(cell, return_inverse=True, return_counts=True)
    again = seen[inv] >= 2
    if not again.any():
        return 0.0, 0.0
    _, cmed, _, _, _ = group_median(inv[again], med[again], med[again])
    _, back = np.unique(inv[again], return_inverse=True)
    return robust_rms(med[again] - cmed[back]), float(np.median(sd[again]))


def screen_floor(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
                 storage: Storage, cell_m: float, step_z_m: float, noise_m: float, sensor_m: float,
                 max_error_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, bool]:
    """The floor candidates that are the floor: (the mask kept, the height from the crossings at the floor's
    level when most were dropped, a note when some were, whether the walls' feet confirm it); `_screen` without
    its tolerance."""
    kept, shift, note, _, confirmed = _screen(p, t, knots, wall, floor, storage, cell_m, step_z_m, noise_m, sensor_m,
                                              max_error_m)
    return kept, shift, note, confirmed


def _screen(p: np.ndarray, t: np.ndarray, knots: np.ndarray, wall: np.ndarray, floor: np.ndarray,
            storage: Storage, cell_m: float, step_z_m: float, noise_m: float, sensor_m: float,
            max_error_m: float) -> tuple[np.ndarray, np.ndarray | None, str | None, float, bool]:
    """The floor candidates that are the floor: (the mask kept, ..., a note when some were dropped, the
    tolerance: how far from the floor's level a candidate is still floor, inf where no level was found; whether
    what is seen at the walls comes down to the level, `floor_unconfirmed_note`).

    A flat pile top can pass the per-interval vote (nothing below it in that interval) and then anchors the
    height on itself. Across the flight it cannot hide: the crossings alone (no floor) put every time's
    points in one frame up to a constant, and in that frame the floor is one level, the lowest flat one,
    and no wall is seen below it (walls stand on the floor). So, in that frame: the candidates' heights per
    knot interval and cell; the floor's level is their lowest peak (as the vote's outermost peak), read in a
    window as tall as a flat floor's heights scatter (`level_window`), not the frame's spread on slopes; it must
    not lie above the walls' lowest points (beyond stray returns); the
    candidates within BAND noise levels of it are kept, the rest dropped, each judged within the frame's own
    uncertainty between its time and the level's (`knot_covariance`: where the crossings tie two stretches of the
    flight only loosely, the frame's stretches float apart). None kept: the height comes from the crossings alone.

    A floor meets the walls it runs to, so where the level is the floor, what is seen at a wall comes down to it
    unless the pile covers every wall's foot. There the level may still be the floor, seen in a gap between heaps
    (the paper's pile 2), or the bottom of a hollow in a pile that hides the floor wall to wall: the same shape,
    one flat at the floor and one curving at 0.7 m, and nothing else in the data tells them apart: the caller
    decides (`floor_unconfirmed_note`)."""
    if not floor.any():
        return floor, None, None, math.inf, False
    cov: list[np.ndarray] = []
    z_rel, _ = vertical_from_crossings(p, t, knots, wall, np.zeros_like(floor), storage, cell_m, step_z_m, noise_m,
                                       max_error_m, significant_only=False, cov_out=cov)
    if z_rel is None:
        return floor, None, None, math.inf, False
    zc = p[:, 2] + np.interp(t, knots, z_rel)
    k, _ = knot_basis(t, knots)
    nx, ny, cid = grid_cells(p, storage, cell_m)
    key = k * (nx * ny) + cid
    # the frame's noise: how far one interval's height of a cell is from the cell's height at other times
    inside = ~wall & (p[:, 2] < storage.height_m)
    gk, gmed, _, _, gcnt = group_median(key[inside], zc[inside], t[inside])
    many = gcnt >= MIN_CELL_POINTS
    gcell, gmed = gk[many] % (nx * ny), gmed[many]
    spread = between_times_scatter_m(gcell, gmed)
    tol = BAND * max(spread, sensor_m, noise_m)
    # the same with each cell's slope taken out (two passes that hit a sloped cell in different places): the
    # frame's own misalignment between times, which a flat floor's heights carry too
    zs = zc - cell_slopes(np.column_stack([p[:, :2], zc]), cid, nx * ny, cell_m, ny, inside)
    _, smed, _, _, _ = group_median(key[inside], zs[inside], t[inside])
    frame_m = between_times_scatter_m(gcell, smed[many])
    fk, fmed, _, _, fcnt = group_median(key[floor], zc[floor], t[floor])
    # the lowest level that holds more than stray points (nothing but noise is below the floor); not the
    # highest peak: a broad flat top can out-number the floor seen (measured: 350 against 100 points)
    order = np.argsort(fmed)
    fmed, fcnt, fk = fmed[order], fcnt[order], fk[order]
    stray_f = max(MIN_VOTES, STRAY_FRACTION * float(np.sum(fcnt)))
    if lowest_window(fmed, fcnt, tol, stray_f) is None:
        return np.zeros_like(floor), None, ("no floor seen: too few floor points agree on one level once the "
                                            "crossings align the flight; the height is corrected from the crossings "
                                            "alone"), math.inf, False
    # The level within the floor's own scatter, not the frame's: under a degree of pointing noise the frame's
    # spread (on slopes) reached 0.7 m, and a window that wide over a pile that hides most of the floor took in
    # the toe's ramp above the few floor cells seen (its median 0.6-0.9 m up the toe: Appendix A, pile 2).
    width = level_window(fk % (nx * ny), fmed, fcnt, noise_m, frame_m, tol)
    i0, i1 = lowest_window(fmed, fcnt, width, stray_f) or lowest_window(fmed, fcnt, tol, stray_f)
    level = float(np.median(fmed[i0:i1]))
    # everything seen at a wall (its face or the floor or pile against it), the horizontal correction applied:
    # nothing there is below the floor
    band = BAND * max(sensor_m, noise_m)
    at_wall = ((p[:, 0] < band) | (p[:, 0] > storage.length_m - band) | (p[:, 1] < band)
               | (p[:, 1] > storage.width_m - band))
    walls_z = np.sort(zc[at_wall])
    stray = int(max(MIN_VOTES, STRAY_FRACTION * len(walls_z)))
    wall_low = float(walls_z[stray]) if len(walls_z) > stray else math.inf
    if level > wall_low + tol:
        return np.zeros_like(floor), None, (f"no floor seen: what the vote took for it lies {level - wall_low:.2f} m "
                                            "above the walls' lowest points once the crossings align the flight (a "
                                            "flat pile top); the height is corrected from the crossings alone"), \
            tol, False
    confirmed = int(np.count_nonzero(np.abs(walls_z - level) <= tol)) >= MIN_VOTES
    # A candidate is judged against the level within the frame's own uncertainty between its time and the level's:
    # where the crossings tie two stretches of the flight loosely (a loop whose long legs see the pile's flanks once),
    # the frame's halves float apart, and a floor seen in one lies above the other's level (measured: 0.10 m on a
    # flight's true pose, 0.33 m with a barometer's walk; the far end's floor dropped as a flat pile top).
    reach = np.full(len(fk), tol)
    if cov:
        c = cov[0]
        lk = fk[i0:i1] // (nx * ny)
        var = np.diag(c) + float(np.mean(c[np.ix_(lk, lk)])) - 2.0 * np.mean(c[:, lk], axis=1)
        reach = np.hypot(tol, BAND * np.sqrt(np.maximum(var, 0.0)))[np.minimum(fk // (nx * ny), len(knots) - 1)]
    good_keys = fk[np.abs(fmed - level) <= reach]
    kept = floor & np.isin(key, good_keys)
    dropped = int(np.count_nonzero(floor & ~kept))
    if not 2 * dropped > np.count_nonzero(floor):
        # Most of it is one level: the vote's floor stands as it is. Dropping the few off it cost more than it
        # gave (measured on pile 1, which has no flat top: the crossings' frame misaligns some true floor by
        # a few decimetres on a `flow` flight; Ve 0.16 % -> 2.0 %); the joint solve's Huber loss outvotes them.
        return floor, None, None, tol, confirmed
    # The floor kept is the level's own cluster: a floor is flat, so its heights scatter by their own noise, not by
    # the crossings' spread on slopes, which under a degree of pointing noise reached 0.7 m and kept a pile's toe
    # as floor (the joint solve on it then put the level 0.6 m off: Appendix A, `vio`, pile 2)
    half = floor_half_width(fmed[i0:i1], level, tol, noise_m, fcnt)
    kept = floor & np.isin(key, fk[np.abs(fmed - level) <= half])
    note = (f"{dropped} of {int(np.count_nonzero(floor))} floor points dropped: more than {tol:.2f} m above the "
            "floor's level once the crossings align the flight (a flat pile top)")
    # Most of what the vote called floor was a flat top: the remaining floor is too sparse to anchor each
    # interval (measured: the joint solve over it kept a 0.19 m bias on a pile-2 flight); the crossings'
    # own solution, put at the floor's level, is used instead.
    return kept, z_rel - level, note, tol, confirmed


def floor_unconfirmed_note(z: np.ndarray, confirmed: bool, open_shift_m: float) -> str | None:
    """Why a height anchored on a floor the walls' feet do not confirm (`_screen`) is not kept (None: it is): it moves
    the height (z, the knots', against the crossings alone, whose mean is the logged reference's) by more than
    open_shift_m on average, the most the logged height is believed to be off. Within it, were the floor a hollow,
    it could do no more harm than the logged height's own error."""
    shift = abs(float(np.mean(z)))
    if confirmed or shift <= open_shift_m:
        return None
    return (f"no floor confirmed: what the vote took for it was seen only away from the walls (the pile covers their "
            f"feet), so it may be a hollow in the pile, and it would move the height by {shift:.2f} m, more than the "
            f"barometer is believed to drift in the flight ({open_shift_m:.2f} m); the height is corrected from the "
            "crossings alone, at the logged height's level")


def open_floor_note(how: str, shift_m: float) -> str:
    """The pose line's note on a height anchored (how: "anchored", "solved again") on a floor the walls' feet do not
    confirm, which moved it shift_m on average."""
    return (f"the floor the height was {how} on was seen only away from the walls (the pile covers their feet): were "
            f"it a hollow in the pile, the height would be off by up to {abs(shift_m):.2f} m, what anchoring on it "
            "moved it")


def lowest_window(med_m: np.ndarray, counts: np.ndarray, width_m: float, stray: float) -> tuple[int, int] | None:
    """The lowest window width_m tall of the sorted heights med_m (counts points each) that holds more than stray
    points, as the index range [i, j) of its heights (None: none does). Nothing but noise is below the floor."""
    cum = np.concatenate([[0], np.cumsum(counts)])
    upto = np.searchsorted(med_m, med_m + width_m, side="right")
    dense = np.flatnonzero(cum[upto] - cum[:-1] > stray)
    return (int(dense[0]), int(upto[dense[0]])) if len(dense) else None


def level_window(cell: np.ndarray, med_m: np.ndarray, counts: np.ndarray, noise_m: float, frame_m: float,
                 tol_m: float) -> float:
    """How tall a window of floor heights (one knot interval's median in a cell each) the floor's level is read in:
    BAND times the larger of the candidates' own scatter (in the cells seen at more than one time, about each
    cell's median), a typical height median's noise, and the crossings frame's misalignment between times
    (frame_m: measured with the cells' slopes taken out); never over tol (the frame's spread over the whole
    surface, slopes and all: under a degree of pointing error a point on a slope moves up or down by the slope
    times 0.2 m, which a flat floor's heights do not)."""
    typical = noise_m / math.sqrt(max(float(np.median(counts)), 1.0)) if len(counts) else noise_m
    return min(tol_m, BAND * max(between_times_scatter_m(cell, med_m), typical, frame_m))


def between_times_scatter_m(cell: np.ndarray, med_m: np.ndarray) -> float:
    """How far one knot interval's height of a cell (med_m, the cells' ids in cell) is from the cell's median
    height over the times it was seen: the robust RMS over the cells seen more than once (0: none was)."""
    _, inv, seen = np.unique(cell, return_inverse=True, return_counts=True)
    again = seen[inv] >= 2
    if not again.any():
        return 0.0
    _, cell_med, _, _, _ = group_median(inv, med_m, med_m)  # per cell (inv: 0 .. cells - 1)
    return robust_rms((med_m - cell_med[inv])[again])


def floor_half_width(lowest_m: np.ndarray, level_m: float, tol_m: float, noise_m: float, counts: np.ndarray) -> float:
    """How far from the floor's level a floor height (one knot interval's median in a cell) is still floor, once
    most of the vote's floor was a flat top: BAND times the scatter of the lowest window's heights about the level
    (a floor is flat, so that is their own noise), never under BAND sd's of a typical height's median, never over
    tol (the crossings' spread, which on a pile's slopes under pointing noise reaches its toe)."""
    typical = noise_m / math.sqrt(max(float(np.median(counts)), 1.0)) if len(counts) else noise_m
    scatter = robust_rms(np.asarray(lowest_m) - level_m) if len(lowest_m) else 0.0
    return min(tol_m, BAND * max(scatter, typical))
