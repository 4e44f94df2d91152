"""What the report says of the pose correction (`ground.pose_correction`): the line describing what it applied, and
the warnings for a corrected path near a wall, a height not tied to the floor, and components the building did not
constrain."""

from __future__ import annotations

from ground.pose_correction import PoseCorrection
from ground.pose_height import MIN_TIE_CELLS

WALL_WARNING_M = 0.5
"""A corrected path nearer a wall or the roof than this is warned about: the clearance the SITL's missions keep
by default (a 450-class quadcopter reaches 0.35 m from its centre with its propellers)."""


def wall_warning(corr: PoseCorrection) -> str | None:
    """A warning when the corrected path came nearer a wall or the roof than WALL_WARNING_M, or None."""
    if corr.closest_wall is None or corr.closest_wall[0] >= WALL_WARNING_M:
        return None
    distance, surface, _, since = corr.closest_wall
    where = f"{-distance:.2f} m beyond {surface}" if distance < 0 else f"to {distance:.2f} m from {surface}"
    return (f"the corrected flight path came {where} {since:.0f} s after the log's start: the vehicle flew that "
            "close to the building on a drifting estimate (its propellers may have touched it); give the next flight "
            "more room from the walls (a larger P_traj)")


def describe(corr: PoseCorrection) -> str:
    """One line for the report: the correction applied, its size over time, and where the data did not
    constrain it."""
    s = corr.size()
    line = (f"pose corrected from the building: horizontal {s['horizontal_rms_m']:.2f} m RMS "
            f"({s['horizontal_max_m']:.2f} max), vertical {s['vertical_rms_m']:.2f} m RMS "
            f"({s['vertical_max_m']:.2f} max), heading "
            f"{s['heading_rms_deg']:.2f} deg RMS ({s['heading_max_deg']:.2f} max) over time; the floor and walls "
            f"now {corr.rms_after_m * 100:.1f} cm off their planes (were {corr.rms_before_m * 100:.1f} cm)")
    sh = corr.sweep_heights
    sweeps = ([] if sh is None else
              [f"the height refined sweep by sweep from the floor {sh.sweeps_used} of {sh.sweeps} sweeps saw, by "
               f"{sh.rms_m() * 100:.1f} cm RMS ({sh.shrink * 100:.0f} % of what they measured kept against their "
               "scatter)"])
    return "; ".join([line, *sweeps, *corr.notes])


def unanchored_warning(corr: PoseCorrection) -> str | None:
    """A warning when the corrected height was not tied to the floor over part of the flight (`floor_anchored`), or
    None."""
    total, t0, t1 = corr.height_unanchored_s
    if not corr.applied or not total > 0 or len(corr.knot_t_s) < 2:
        return None
    flown = float(corr.knot_t_s[-1] - corr.knot_t_s[0])
    return (f"the corrected height is not tied to the floor for {total:.0f} of the {flown:.0f} s flown (the longest "
            f"stretch {t1 - t0:.0f} s, from t = {t0:.1f} s): there no floor was seen, nor enough of the same pile "
            f"({MIN_TIE_CELLS} cells) on other passes that saw it, so the height rests on the pile seen from one "
            "moment to the next, or on a handful of cells, whose errors add up "
            "(decimetres over 100 s, measured where a pile hid the floor); the volume's interval carries the "
            "altitude reference's drift over those stretches, which the data could not check. A flight that sees "
            "the floor along the way (legs farther from the walls) ties it")


def unconstrained_warning(corr: PoseCorrection) -> str | None:
    """A warning naming the components the structure did not constrain over part of the flight (they were
    interpolated between the stretches that did), or None."""
    if not corr.applied or len(corr.knot_t_s) < 2:
        return None
    total = float(corr.knot_t_s[-1] - corr.knot_t_s[0])
    names = {"x": "x (along the length)", "y": "y (along the width)", "z": "height", "heading": "heading"}
    parts = [f"{names[c]} over {s:.0f} s" for c, s in corr.unconstrained_s().items() if s > 0]
    if not parts:
        return None
    return (f"the pose correction is not constrained by the building or the pile seen twice for {', '.join(parts)} "
            f"of the {total:.0f} s flown: there it is interpolated between the stretches that are (no wall across the "
            "sweep, no sloped pile seen on another pass); trajectory errors there are only as small as the drift is "
            "smooth")
