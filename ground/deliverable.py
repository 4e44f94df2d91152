"""What a customer signs, added to the report: who/where/when (ground.metadata), the verdict line and the
piles (ground.piles). Kept apart from ground.report so the volume pipeline stays what it was."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from ground.base import FLOOR_BASE, Base, BaseKind
from ground.metadata import SurveyInfo, limiting_terms, remedies, survey_metadata, verdict
from ground.piles import PileOptions, find_piles, pile_table
from ground.surface import Grid
from ground.uncertainty import DEFAULT_INTERVAL_MODEL, ErrorTerms, SurveyErrors
from ground.volume_warnings import regions


def add_deliverable(report: dict[str, Any], *, header: dict, log_path: Path, t_s: np.ndarray | None,
                    info: SurveyInfo, piles: PileOptions, heights_fit: np.ndarray, heights: np.ndarray, grid: Grid,
                    errors: SurveyErrors | None,
                    errors_in: Callable[[np.ndarray], SurveyErrors] | None, base: Base | None = None) -> np.ndarray:
    """report["metadata"], report["piles"], report["verdict"] (and their warnings) and what would narrow the
    interval (report["to_narrow_interval"]), in place. The piles are measured over the survey's base
    (`Base.pile_heights`), their intervals with its own error. Returns the piles' cells (`Assignment.labels`),
    which the site map outlines."""
    meta, warnings = survey_metadata(header, info, log_path, t_s)
    report["metadata"] = meta
    sigma = errors.point_sigma_m if errors is not None else 0.0
    base = base or FLOOR_BASE
    above = base.pile_heights(heights)
    found = find_piles(above, grid, sigma, piles)
    table = pile_table(above, grid, sigma, piles, errors_in, over=base.piles_over,
                       extra_over=None if base.kind is BaseKind.SURVEY else base.extra_over, found=found)
    report["piles"] = table
    report["warnings"] = [*report.get("warnings", []), *warnings, *table["warnings"]]
    report["volume_unit"] = piles.volume_unit.value
    report["mass_unit"] = piles.mass_unit.value
    terms = report.get("interval_terms_m3")
    own = None if base.kind is BaseKind.FLOOR else (
        "earlier_survey" if base.kind is BaseKind.SURVEY else "fitted_floor",
        max(base.extra_below_m3, base.extra_above_m3))
    limits = [] if terms is None else limiting_terms(ErrorTerms(**terms), DEFAULT_INTERVAL_MODEL, own)
    report["verdict"] = _verdict(report, limits, heights_fit, heights, grid, piles)
    report["to_narrow_interval"] = remedies(limits)
    return found.labels


def _verdict(report: dict[str, Any], limits: list[str], heights_fit: np.ndarray, heights: np.ndarray, grid: Grid,
             piles: PileOptions) -> str:
    where = None
    if "unseen" in limits:
        filled = ~np.isfinite(heights_fit)
        weight = np.where(filled & np.isfinite(heights), np.clip(heights, 0, None), 0.0) * grid.cell_area_m2
        found = regions(filled, weight, grid, n=1)
        where = found[0][1] if found else None
    vu = piles.volume_unit
    return verdict(report["volume_m3"], report.get("volume_interval_m3"), limits, where,
                   len(report.get("warnings", [])), vu.symbol, vu.m3_per_unit, report.get("volume_other_reading"))
