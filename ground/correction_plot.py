"""The trajectory correction over time, as a figure: what the report added to the autopilot's logged pose.

The report's text gives the correction's size (RMS and largest); the drone engineer who flew the survey wants to
see *when* it was large: a drift that grew along a leg, a heading that slipped in a turn, the height raised where the
pile was below a rangefinder-fed EKF. Two panels on the log's clock: the position's shift in the storage frame W
(x, y, and the height, which includes the rangefinder's share taken out, drawn dashed on its own) and the heading's
change. Stretches where the floor and walls did not set a component are shaded: there it was interpolated.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from matplotlib.axes import Axes
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from ground.plots import DPI, FIGSIZE_IN, save_png
from ground.pose_correction import PoseCorrection
from ground.pose_knots import Component
from ground.rangefinder_height import RangefinderShare

FIGURE_NAME = "trajectory_correction"
"""The figure's name in the report (its PNG is FIGURE_NAME.png)."""
UNCONSTRAINED_COLOUR = "0.88"


@dataclass(frozen=True)
class CorrectionSeries:
    """The correction on one time grid (the log's clock).

    Attributes:
        t_s: (N,) times.
        shift_w_m: (N, 3) the position's total shift in W (x, y, up), the rangefinder's lift included.
        heading_deg: (N,) the heading's change about W's z (deg: a figure's unit).
        lift_m: (N,) the rangefinder's share taken out (part of shift_w_m's height); None when not applied.
        free_z_s, free_heading_s: the (start, end) stretches where the height / heading was interpolated.
    """

    t_s: np.ndarray
    shift_w_m: np.ndarray
    heading_deg: np.ndarray
    lift_m: np.ndarray | None
    free_z_s: tuple[tuple[float, float], ...] = ()
    free_heading_s: tuple[tuple[float, float], ...] = ()


def _free_stretches(pose: PoseCorrection, component: Component) -> tuple[tuple[float, float], ...]:
    """The (start, end) times of the knot intervals the structure did not set (`PoseCorrection.free_intervals`)."""
    k = pose.knot_t_s
    free = pose.free_intervals(component) if len(k) >= 2 else None
    return () if free is None else tuple((float(k[i]), float(k[i + 1])) for i in np.flatnonzero(free))


def correction_series(pose: PoseCorrection | None, rangefinder: RangefinderShare | None) -> CorrectionSeries | None:
    """The report's corrections on a common grid (the lift's, or the knots'), or None when none was applied (a lever
    arm placed in place of a drift moves the points, not the trajectory: its knots stay zero, and the report names it
    in words)."""
    posed = pose is not None and pose.applied and pose.lever_change_m is None and len(pose.knot_t_s) >= 2
    lifted = rangefinder is not None and rangefinder.applied and len(rangefinder.lift_t_s) >= 2
    if not posed and not lifted:
        return None
    t = np.asarray(rangefinder.lift_t_s if lifted else pose.knot_t_s, dtype=float)
    if posed and lifted:  # the knots too: the correction is linear between them, its corners are there
        t = np.union1d(t, np.asarray(pose.knot_t_s, dtype=float))
    corr = pose.at(t) if posed else np.zeros((len(t), 4))
    lift = rangefinder.lift_at(t) if lifted else None
    shift = corr[:, :3].copy()
    if lift is not None:
        shift[:, 2] += lift
    return CorrectionSeries(t, shift, np.degrees(corr[:, 3]), lift,
                            _free_stretches(pose, Component.Z) if posed else (),
                            _free_stretches(pose, Component.HEADING) if posed else ())


def _shade(ax: Axes, stretches: tuple[tuple[float, float], ...]) -> None:
    for t0, t1 in stretches:
        ax.axvspan(t0, t1, color=UNCONSTRAINED_COLOUR, zorder=0, linewidth=0)


def correction_figure(series: CorrectionSeries, title: str = "Trajectory correction over time") -> Figure:
    """Position shift (m) and heading change (deg) against time, unconstrained stretches shaded."""
    fig = Figure(figsize=FIGSIZE_IN, dpi=DPI, layout="constrained")
    FigureCanvasAgg(fig)
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=(2, 1))
    t = series.t_s
    _shade(top, series.free_z_s)
    for c, (name, colour) in enumerate((("x (along the length)", "tab:blue"), ("y (along the width)", "tab:orange"),
                                        ("height", "tab:green"))):
        top.plot(t, series.shift_w_m[:, c], color=colour, linewidth=1.2, label=name)
    if series.lift_m is not None:
        top.plot(t, series.lift_m, color="tab:green", linestyle="--", linewidth=1.0,
                 label="of the height: the rangefinder's share taken out")
    handles = top.get_legend_handles_labels()[0]
    if series.free_z_s:
        handles.append(Patch(color=UNCONSTRAINED_COLOUR, label="height not set by the floor (interpolated)"))
    top.legend(handles=handles, fontsize="small", loc="best", framealpha=0.85)
    top.axhline(0.0, color="0.4", linewidth=0.6)
    top.set_ylabel("position shift [m]")
    top.set_title(title)
    _shade(bottom, series.free_heading_s)
    bottom.plot(t, series.heading_deg, color="tab:purple", linewidth=1.2)
    if series.free_heading_s:  # its own key: shaded here means the heading, not the height, was left free
        bottom.legend(handles=[Patch(color=UNCONSTRAINED_COLOUR, label="heading not set by the walls (interpolated)")],
                      fontsize="small", loc="best", framealpha=0.85)
    bottom.axhline(0.0, color="0.4", linewidth=0.6)
    bottom.set_ylabel("heading change [deg]")
    bottom.set_xlabel("time [s] (the sample log's clock)")
    span = float(np.max(np.abs(series.heading_deg), initial=0.0))
    if not span > 0.05:  # a flat line at 0 would be drawn with a range of 1e-16: say the scale instead
        bottom.set_ylim(-0.1, 0.1)
    for ax in (top, bottom):
        ax.grid(True, linewidth=0.4, alpha=0.5)
        if len(t) and math.isfinite(t[0]) and t[-1] > t[0]:
            ax.set_xlim(t[0], t[-1])
    return fig


def plot_correction(series: CorrectionSeries, out_png: str | Path, title: str = "Trajectory correction over time"
                    ) -> Path:
    """Write the figure (see `correction_figure`) and return the PNG path."""
    return save_png(correction_figure(series, title), out_png)
