"""A report's output files beside its text: the point cloud, and its figures as jobs drawn on two cores
(`ground.figure_jobs`): the engineer's three (cloud, height map, coverage), the customer's three (site map, 3D view,
cross-sections: `ground.page_figures`) and the trajectory's correction when one was applied
(`ground.correction_plot`). Matplotlib is imported only when figures are drawn."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ground.base import BaseKind
from ground.survey import Survey


def height_map_title(survey: Survey, volume_m3: float) -> str:
    """The height map shows heights above z = 0; over another base its volume is not the map's, so it says so."""
    from ground.render import signless_zero
    v = f"{signless_zero(volume_m3, '.1f'):,.1f} m³"
    base = survey.base
    if base is None or base.kind is BaseKind.FLOOR:
        return f"Fitted surface: {v}"
    over = "the fitted floor" if base.kind is BaseKind.FITTED_FLOOR else "change since the earlier survey"
    return f"Fitted surface, heights above z = 0 ({over}: {v})"


def write_outputs(survey: Survey, report: dict, out: Path, plots: bool,
                  pile_labels: np.ndarray | None = None) -> dict[str, Path]:
    """Point cloud and (optionally) the figures, drawn on two cores where there are two (ground.figure_jobs)."""
    from ground.figure_jobs import draw
    from ground.render import write_ply
    write_ply(survey.pile_points_w, out / "cloud.ply")
    if not plots:
        return {}
    return draw(figure_jobs(survey, report, out, pile_labels))


def figure_jobs(survey: Survey, report: dict, out: Path, pile_labels: np.ndarray | None = None) -> list:
    """The report's figures as jobs (`ground.figure_jobs.FigureJob`), their costs as measured on the benchmark's
    survey: the engineer's three, the customer's three, and the trajectory's correction when one was applied."""
    from ground import plots as p
    from ground.exports.contours import contour_lines
    from ground.figure_jobs import FigureJob
    lw = (survey.storage.length_m, survey.storage.width_m)
    path = survey.cloud.path_w[:: max(1, len(survey.cloud.path_w) // 5000)]
    ra = report["coverage_ratio_pct"]
    g = survey.grid
    return [
        FigureJob("cloud", p.plot_cloud_top, (survey.pile_points_w, path, lw, out / "cloud_top.png"),
                  {"title": f"Point cloud, top view ({len(survey.pile_points_w)} points)"}, 0.48),
        FigureJob("height_map", p.plot_height_map, (g.x_edges, g.y_edges, survey.heights, lw, out / "height_map.png"),
                  {"title": height_map_title(survey, report["volume_m3"]), "filled": ~np.isfinite(survey.heights_fit),
                   "contours": contour_lines(survey.heights, g)}, 0.47),
        FigureJob("coverage", p.plot_coverage, (g.x_edges, g.y_edges, survey.counts, np.isfinite(survey.heights_fit),
                                                lw, out / "coverage.png"),
                  {"title": f"Coverage (R_a = {ra:.1f} %)",
                   "bridged": survey.bridged}, 0.44),
        *page_figure_jobs(survey, report, out, path, pile_labels),
        *correction_figure_jobs(survey, out),
    ]


def correction_figure_jobs(survey: Survey, out: Path) -> list:
    """The trajectory's correction over time (ground.correction_plot), when the report applied one."""
    from ground.correction_plot import FIGURE_NAME, correction_series, plot_correction
    from ground.figure_jobs import FigureJob
    series = correction_series(survey.pose, survey.rangefinder)
    return [] if series is None else [FigureJob(FIGURE_NAME, plot_correction, (series, out / f"{FIGURE_NAME}.png"),
                                                cost_s=0.3)]


def page_figure_jobs(survey: Survey, report: dict, out: Path, path_w: np.ndarray,
                     pile_labels: np.ndarray | None = None) -> list:
    """The customer's figures (ground.page_figures): the labelled map (with the piles' outlines: pile_labels, the
    cells the pile table sums), the 3D view and the cross-sections."""
    from ground import page_figures as f
    from ground.figure_jobs import FigureJob
    from ground.piles import VolumeUnit
    g, lw = survey.grid, (survey.storage.length_m, survey.storage.width_m)
    site = report.get("site") or {}
    heading = site.get("heading_deg") if isinstance(site, dict) else None
    vu = VolumeUnit(report.get("volume_unit", VolumeUnit.M3.value))
    base = survey.base.heights_m if survey.base is not None else None
    filled = ~np.isfinite(survey.heights_fit)  # what the empty-cell policy put where no surface reached
    return [
        FigureJob(f.SITE_MAP, f.plot_site_map, (out / f"{f.SITE_MAP}.png", g.x_edges, g.y_edges, survey.heights, lw,
                                                report.get("piles"), heading, path_w, vu.symbol, vu.m3_per_unit),
                  {"filled": filled, "pile_labels": pile_labels}, 0.66),
        FigureJob(f.SURFACE_3D, f.plot_surface_3d, (out / f"{f.SURFACE_3D}.png", g.x_edges, g.y_edges, survey.heights,
                                                    lw), cost_s=0.69),
        FigureJob(f.SECTIONS, f.plot_sections, (out / f"{f.SECTIONS}.png", g.x_edges, g.y_edges, survey.heights, lw,
                                                survey.pile_points_w, base, report.get("piles")),
                  {"filled": filled}, 0.50),
    ]
