"""Warnings that say what is wrong with a volume, and where, when it matters to the interval.

Each fires from one of the interval's error terms (ground.uncertainty) when that term is what makes
the interval wide, so a clean survey stays quiet and a corner pile flown too sparsely does not:

- **unseen material**: the fill put material into cells no surface reached, and that is a large
  part of the interval; named by the regions' extents in the storage frame.
- **faces**: cells whose points lie metres apart vertically (an overhang or a vertical face): whenever a
  face runs over a few cells (the interval is not calibrated for such surfaces), or their share of the
  interval is large.
- **pose**: the height of the drifting pose, as corrected from the building, holds most of a wide
  interval: the floor seen too seldom to pin the altitude reference.
- **level**: the height's level rests on the logged altitude reference (no floor the flight confirmed
  pinned it), and its drift holds most of a wide interval.
- **wide interval**: the interval is wider than the surveyor's tolerance (an option), so the survey
  needs more coverage to be useful.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
from scipy import ndimage

from ground.piles import MIN_PILE_CELLS
from ground.render import signless_zero
from ground.surface import Grid, fill_empty
from ground.uncertainty import ErrorTerms, FaceCells, IntervalModel, over_surface_m3

DOMINANT_SHARE = 0.5
"""A term 'dominates' when it holds over half of the interval's variance (its square over the sum)."""
DEFAULT_MAX_INTERVAL_PCT = 5.0
"""Default tolerance: a 90 % interval wider than +/-5 % of the volume is too wide to sign without a
warning (stockpile audits typically accept 1-5 %); `pilescan-ground report --max-interval-pct`."""
MAX_REGIONS = 3
MIN_FACE_CELLS = MIN_PILE_CELLS
"""Face cells from this many on are a face the interval may not hold, whatever their share of it. The interval is
calibrated on surfaces one height per cell can hold (tools/calibrate_interval.py FACES_FAMILIES): a box at P_traj
20 % reads 19 % high with a faces term of 0.4 % of its volume. On the evaluation set every box and undercut sphere
showed 4 to 375 face cells; of the 1,260 runs of the families but these and the bays, 15 showed any, 1 or 2 lone cells
(a stray return), none more; 89 of the 126 bay piles, against their walls, showed 4 or more. It is the least cells
the report names as a pile: a face is held to the size of a pile."""


def _share(scaled: float, t: ErrorTerms, model: IntervalModel, high: bool) -> float:
    below, above = model.half_widths_m3(t)
    total = (above if high else below) ** 2
    return scaled**2 / total if total > 0 else 0.0


def _within_half_tolerance(m3: float, volume_m3: float | None, max_pct: float) -> bool:
    """Whether m3 (a term's scaled size, or what an anchor moved) is under half the tolerance max_pct of the volume:
    then a warning of it would tell a survey that signs what it need not hear (no volume given: never)."""
    return volume_m3 is not None and volume_m3 > 0 and abs(m3) < 0.5 * max_pct / 100.0 * volume_m3


def _holds_wide_interval(scaled: float, t: ErrorTerms, model: IntervalModel, volume_m3: float | None,
                         max_pct: float, high: bool = False) -> bool:
    """Whether a term (scaled: its factor times it, m³) holds over half the interval's variance on that side and,
    given the volume, widens it by more than half the tolerance: when the unseen, pose and level warnings speak."""
    if scaled <= 0 or _share(scaled, t, model, high) < DOMINANT_SHARE:
        return False
    return not _within_half_tolerance(scaled, volume_m3, max_pct)


def regions(mask: np.ndarray, weight_m3: np.ndarray, grid: Grid, n: int = MAX_REGIONS) -> list[tuple[float, str]]:
    """The n heaviest connected regions of mask as (m³, where), heaviest first: where is 'x a-b m, y c-d m', or, for a
    strip along the walls spanning the building, those walls (`along_walls`)."""
    labels, k = ndimage.label(mask)
    if k == 0:
        return []
    sums = ndimage.sum(weight_m3, labels, index=np.arange(1, k + 1))
    boxes = ndimage.find_objects(labels)
    cx, cy = grid.length_m / grid.shape[0], grid.width_m / grid.shape[1]
    out = []
    for i in np.argsort(sums)[::-1][:n]:
        sx, sy = boxes[i]
        box = (f"x {math.floor(sx.start * cx)}-{math.ceil(sx.stop * cx)} m, "
               f"y {math.floor(sy.start * cy)}-{math.ceil(sy.stop * cy)} m")
        out.append((float(sums[i]), along_walls(labels == i + 1, grid) or box))
    return out


WALL_SHARE = 0.25
"""A region runs along a wall when it holds at least this share of the cells at that wall's foot."""


def along_walls(region: np.ndarray, grid: Grid) -> str | None:
    """A region that spans the building (a strip along several walls, as the fill leaves beside a pile that
    reaches them) named by those walls and how far from them it reaches: "the walls x = 0 m and y = 40 m (within
    3 m)", where its bounding box would say only "x 0-60 m, y 0-40 m". None for a region that does not span half
    the building both ways, runs along no wall, or reaches further in than a quarter of the narrower side."""
    nx, ny = region.shape
    xs, ys = np.nonzero(region)
    if len(xs) == 0 or np.ptp(xs) + 1 < nx / 2 or np.ptp(ys) + 1 < ny / 2:
        return None
    cx, cy = grid.length_m / nx, grid.width_m / ny
    feet = {"x = 0 m": region[0, :].mean(), f"x = {grid.length_m:g} m": region[-1, :].mean(),
            "y = 0 m": region[:, 0].mean(), f"y = {grid.width_m:g} m": region[:, -1].mean()}
    walls = [name for name, share in feet.items() if share >= WALL_SHARE]
    if not walls:
        return None
    # each cell's distance in from the nearest wall, the region's 90th percentile of it
    depth = np.minimum(np.minimum(xs + 1, nx - xs) * cx, np.minimum(ys + 1, ny - ys) * cy)
    reach_m = float(np.percentile(depth, 90))
    if reach_m > 0.25 * min(grid.length_m, grid.width_m):
        return None
    named = walls[0] if len(walls) == 1 else ", ".join(walls[:-1]) + " and " + walls[-1]
    return f"the wall{'s' if len(walls) > 1 else ''} {named} (within {math.ceil(reach_m)} m)"


def unseen_warning(heights_fit: np.ndarray, heights: np.ndarray, grid: Grid, t: ErrorTerms,
                   model: IntervalModel, volume_m3: float | None = None,
                   max_pct: float = DEFAULT_MAX_INTERVAL_PCT) -> str | None:
    """When the filled cells hold material, dominate the interval, and (given the volume) widen it by more
    than half the tolerance max_pct: a survey whose whole interval is a fraction of a percent need not
    hear that most of that fraction is unseen floor."""
    scaled = model.unseen_m3(t)
    if not _holds_wide_interval(scaled, t, model, volume_m3, max_pct, t.unseen_high_m3 > t.unseen_low_m3):
        return None
    filled = ~np.isfinite(heights_fit)
    left_empty = not np.isfinite(heights[filled]).any()  # --empty-cells leave: the material is missing
    shown = fill_empty(heights_fit, "nearest") if left_empty else heights
    weight = np.where(filled & np.isfinite(shown), np.clip(shown, 0, None), 0.0) * grid.cell_area_m2
    where = regions(filled, weight, grid)
    area = float(filled.sum() * grid.cell_area_m2)
    listed = "; ".join(f"{w:,.0f} m³ at {box}" for w, box in where if w >= 0.01 * where[0][0])
    what = ("it was left out, and the nearest surface suggests" if left_empty else "the fill put")
    return (f"{area:,.0f} m² of floor was never seen and {what} {float(weight.sum()):,.0f} m³ there "
            f"({listed}): most of the volume's uncertainty is there; fly closer tracks (lower P_traj) or "
            "over those areas")


def faces_warning(faces: FaceCells, grid: Grid, t: ErrorTerms, model: IntervalModel) -> str | None:
    """When cells hold points far apart vertically: a face of MIN_FACE_CELLS or more, which the interval is not
    calibrated for, or fewer whose share of the interval is large."""
    scaled = model.k_faces * t.faces_m3
    if faces.n == 0 or (faces.n < MIN_FACE_CELLS and _share(scaled, t, model, high=False) < DOMINANT_SHARE / 2):
        return None
    where = regions(faces.mask, faces.excess_m * grid.cell_area_m2, grid)
    return (f"{faces.n} cells ({faces.n * grid.cell_area_m2:,.1f} m²) hold points up to "
            f"{float(faces.excess_m.max()):.1f} m further apart vertically than their slope and the sensor's "
            f"noise allow, around {'; '.join(box for _, box in where)}: an overhang or vertical face, which one "
            "height per cell cannot hold. The volume near it is uncertain beyond the 90 % interval, which is "
            "calibrated on surfaces one height per cell can hold and may not hold here: look at the places named")


def pose_warning(t: ErrorTerms, model: IntervalModel, volume_m3: float | None = None,
                 max_pct: float = DEFAULT_MAX_INTERVAL_PCT) -> str | None:
    """When the corrected height's error (the pose term) dominates the interval and (given the volume) widens it
    by more than half the tolerance max_pct, as `unseen_warning`."""
    scaled = model.k_pose * t.pose_m3
    if not _holds_wide_interval(scaled, t, model, volume_m3, max_pct):
        return None
    pct = f" ({100.0 * scaled / volume_m3:.1f} % of the volume)" if volume_m3 else ""
    return (f"most of the volume's uncertainty is the drifting pose's height: as corrected from the building it "
            f"can still be off by what moves the volume +/-{scaled:,.0f} m³{pct}; the floor pins the altitude "
            "reference where the sweeps see it, so legs nearer the walls, a strip of floor left clear, or an "
            "altitude reference that does not drift over the pile would narrow it")


def level_warning(t: ErrorTerms, model: IntervalModel, volume_m3: float | None = None,
                  max_pct: float = DEFAULT_MAX_INTERVAL_PCT, walk_m_per_sqrt_s: float | None = None) -> str | None:
    """When the level term (the height's level on the logged altitude reference) dominates the interval and (given
    the volume) widens it by more than half the tolerance max_pct, as `pose_warning`; walk_m_per_sqrt_s: the drift
    believed of the reference, which the warning names (`pilescan-ground report --baro-walk`)."""
    scaled = model.k_level * t.level_m3
    if not _holds_wide_interval(scaled, t, model, volume_m3, max_pct):
        return None
    pct = f" ({100.0 * scaled / volume_m3:.1f} % of the volume)" if volume_m3 else ""
    walk = (f" (a walk of {walk_m_per_sqrt_s:g} m/sqrt(s) believed, --baro-walk)" if walk_m_per_sqrt_s else "")
    return (f"no floor the walls' feet confirm pinned the height: its level is the autopilot's logged altitude "
            f"reference, whose drift over the flight{walk} moves the volume by up to +/-{scaled:,.0f} m³{pct}, most "
            "of the interval; a leg that sees a wall's foot or a strip of clear floor would pin it")


OPEN_FLOOR_CONDITION = "the floor seen only away from the walls is a hollow in the pile"
"""The condition under which a survey anchored on such a floor reads as its other reading (report.json's words)."""


@dataclass(frozen=True)
class OtherReading:
    """The survey's volume under a condition the data cannot rule out: had the floor its height was anchored on been a
    hollow in the pile (`open_floor_reading`), or every height been as low as the floor seen below z = 0
    (`ground.floor_check.floor_other_reading`)."""

    moved_m3: float
    """What anchoring on that floor moved the volume (signed): the other reading is the volume less it."""
    volume_m3: float
    interval_m3: tuple[float, float] | None
    """Its 90 % interval, with the level term of the logged altitude reference; None without the level's sigma."""
    condition: str = OPEN_FLOOR_CONDITION
    """What the other reading supposes, as the verdict's "or ... if <condition>" says it (a floor seen low:
    `ground.floor_check.floor_other_reading`)."""

    def as_dict(self) -> dict:
        return {"condition": self.condition, "volume_m3": self.volume_m3,
                "volume_interval_m3": None if self.interval_m3 is None else list(self.interval_m3)}


def open_floor_reading(shift_m: float | None, heights: np.ndarray, grid: Grid, volume_m3: float,
                       max_pct: float = DEFAULT_MAX_INTERVAL_PCT, level_sigma_m: float | None = None,
                       terms: ErrorTerms | None = None, model: IntervalModel | None = None) -> OtherReading | None:
    """When the pose correction anchored the height on a floor seen only away from the walls (shift_m: how far that
    moved it, `PoseCorrection.open_floor_shift_m`) and that moved the volume by more than half the tolerance: the
    other reading, were that floor a hollow in a pile that hides the floor wall to wall (nothing in the data tells
    such a hollow from a floor seen in a gap between heaps). Given the logged level's sigma
    (`PoseCorrection.level_sigma_m`), the survey's terms and the model, with its own interval: the level then rests
    on the logged reference. None otherwise."""
    if not shift_m or not math.isfinite(shift_m):
        return None
    moved = over_surface_m3(shift_m, heights, grid)
    if _within_half_tolerance(moved, volume_m3, max_pct):
        return None
    other = volume_m3 - moved
    interval = None
    if level_sigma_m and terms is not None and model is not None:
        # the level then spans the whole flight, so the untied stretches' own term is in it
        below, above = model.half_widths_m3(replace(terms, level_m3=over_surface_m3(level_sigma_m, heights, grid),
                                                    untied_m3=0.0))
        interval = (max(0.0, other - below), other + above)
    return OtherReading(moved, other, interval)


def open_floor_warning(shift_m: float | None, heights: np.ndarray, grid: Grid, volume_m3: float,
                       max_pct: float = DEFAULT_MAX_INTERVAL_PCT, level_sigma_m: float | None = None,
                       terms: ErrorTerms | None = None, model: IntervalModel | None = None) -> str | None:
    """The warning for `open_floor_reading` (same arguments): what the anchor moved, and the other reading, which the
    90 % interval does not include."""
    other = open_floor_reading(shift_m, heights, grid, volume_m3, max_pct, level_sigma_m, terms, model)
    if other is None:
        return None
    moved = other.moved_m3
    pct = f" ({100.0 * abs(moved) / volume_m3:.1f} % of the volume)" if volume_m3 > 0 else ""
    if other.interval_m3 is not None:
        lo, hi = other.interval_m3
        reading = (f"the volume is about {other.volume_m3:,.0f} m³ instead (90 % interval {lo:,.0f}-{hi:,.0f} m³, the "
                   "logged altitude reference's drift over the flight included), which this report's 90 % interval "
                   "does not include")
    else:
        reading = "the volume is off by about as much, beyond the 90 % interval"
    return (f"the height was anchored on a floor seen only away from the walls (the pile covers their feet), which "
            f"moved it {signless_zero(shift_m, '+.2f'):+.2f} m and the volume {signless_zero(moved, '+,.0f'):+,.0f} "
            f"m³{pct}: were that a hollow in the pile, not the floor, {reading}; a leg that sees a wall's foot or a "
            "strip of clear floor would confirm the floor")


def wide_interval_warning(volume_m3: float, interval_m3: tuple[float, float], max_pct: float, *,
                          explained: bool = True, stock_m3: float | None = None) -> str | None:
    """When the interval's half-width exceeds max_pct of the volume. explained: another warning says why.
    stock_m3: the volume a change is measured against (an earlier survey's): a change near zero is not a
    percentage of itself, so its interval is judged against the stock it changed."""
    half = 0.5 * (interval_m3[1] - interval_m3[0])
    ref = volume_m3 if stock_m3 is None else stock_m3
    if ref <= 0 or not math.isfinite(half):
        return None
    pct = 100.0 * half / ref
    if pct <= max_pct:
        return None
    what = ("the volume's 90 % interval" if stock_m3 is None
            else f"the change's 90 % interval, against the earlier survey's {stock_m3:,.1f} m³,")
    why = ("the other warnings say why (unseen floor, faces, the pose's height or its level)" if explained
           else "the verdict's 'limited by' says which error holds it")
    return (f"{what} is +/-{pct:.1f} % ({interval_m3[0]:,.1f} to {interval_m3[1]:,.1f} m³), wider than the "
            f"{max_pct:g} % tolerance: not known well enough to sign; {why}, else fly a denser mission")
