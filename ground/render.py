"""Report rendering: report.md, a self-contained report.html, and a PLY point cloud.

The report dict comes from the ground pipeline; any headline key may be missing or None (a SITL
run knows the true volume, a real survey does not), so every value is rendered defensively and
shown as "unknown" rather than dropped or raising. Both text formats are built from one
`ReportContent`, so Markdown and HTML cannot disagree on a number.

The HTML is one file with images inlined as base64 data URIs and no external resources: it must
open identically on a site laptop with no network, and be mailable as a single attachment. Every
string that came from the report is HTML-escaped (warnings may quote log contents).
"""

from __future__ import annotations

import base64
import html
import math
import numbers
import os
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any
from urllib.parse import quote

import numpy as np

from firmware_py.core.surface_file import SEEN_RADIUS_M

ImageMap = Mapping[str, str | Path]
"""Image name (e.g. "cloud_top", "height_map", "coverage") -> image file."""

REPORT_TITLE = "pilescan volume report"
UNKNOWN = "unknown"
NOT_APPLICABLE = "none"

SUMMARY_KEYS: tuple[str, ...] = (
    "volume_m3",
    "volume_interval_m3",
    "base",
    "true_volume_m3",
    "volume_error_pct",
    "coverage_ratio_pct",
    "bridged_area_m2",
    "n_samples",
    "n_points_used",
    "n_points_removed_walls",
    "echo",
    "cell_size_m",
    "empty_cell_policy",
    "sensor_noise",
    "pose_source",
    "storage",
    "site",
    "log",
    "source",
    "software_version",
    "elapsed_s",
)
"""Headline keys, in table order; every other top-level key (except warnings) goes to "All figures"."""

REFERENCE_KEYS = ("true_volume_m3", "volume_error_pct")
"""Rows that exist only with a reference volume (a simulated survey, --truth-volume): dropped without one."""
OPTIONAL_KEYS = ("echo", "bridged_area_m2")
"""Rows dropped when the report has nothing to say (no return model for the sensor, a merged survey)."""

_SUMMARY_LABELS: dict[str, str] = {
    "volume_m3": "Stockpile volume",
    "volume_interval_m3": "90 % interval",
    "base": "Measured from (base)",
    "true_volume_m3": "True volume (reference)",
    "volume_error_pct": "Volume error Ve (eq. 8)",
    "coverage_ratio_pct": "Area coverage ratio R_a (eq. 9)",
    "bridged_area_m2": f"… of it with no point within {SEEN_RADIUS_M:g} m (bridged)",
    "n_samples": "LiDAR samples",
    "n_points_used": "Points used for the surface",
    "n_points_removed_walls": "Points removed (walls/roof)",
    "echo": "Echoes",
    "cell_size_m": "Grid cell size",
    "empty_cell_policy": "Empty-cell policy",
    "sensor_noise": "Sensor noise (simulated)",
    "pose_source": "Pose source (autopilot EKF)",
    "storage": "Storage L × W × H",
    "site": "Site (floor corner; x axis heading)",
    "log": "Log blocks",
    "source": "Source",
    "software_version": "Software version",
    "elapsed_s": "Processing time",
}

_CLOUD_CAPTION = "Point cloud, top view (coloured by height, flight path in black)"
_IMAGE_CAPTIONS: dict[str, str] = {
    "cloud": _CLOUD_CAPTION,
    "cloud_top": _CLOUD_CAPTION,
    "height_map": "Fitted height map (hatched: filled, never seen; white: no surface)",
    "coverage": "Coverage: points per cell (white: no points), fitted-surface boundary outlined",
    "site_map": "Site map: heights above the floor with contour lines, each pile's name and volume at its "
                "centroid and its outline (white: the cells its volume sums, toe included), the building's outline, "
                "a scale bar, the flight path and, outlined in red, the ground the survey never saw (filled)",
    "surface_3d": "3D view of the surface (heights exaggerated as stated)",
    "sections": "Cross-sections through the largest pile's peak: the surface (dashed where it was filled, never "
                "seen), the base and the LiDAR points near each line",
    "trajectory_correction": "Trajectory correction over time: what the report added to the autopilot's logged "
                             "position and heading (the height includes the rangefinder's share taken out; shaded: "
                             "not set by the floor and walls, interpolated)",
}
PAGE_IMAGES = ("site_map", "surface_3d", "sections")
"""The customer's figures, shown under the pile table; every other image goes to the engineer's details."""

IMAGE_CHECK_SCRIPT = """
window.addEventListener("load", function () {
  var imgs = document.images, ok = 0;
  for (var i = 0; i < imgs.length; i++) { if (imgs[i].complete && imgs[i].naturalWidth > 0) { ok++; } }
  document.documentElement.setAttribute("data-images-total", String(imgs.length));
  document.documentElement.setAttribute("data-images-loaded", String(ok));
  document.documentElement.setAttribute("data-page-width", String(document.documentElement.scrollWidth));
  document.documentElement.setAttribute("data-view-width", String(window.innerWidth));
});
"""
"""The page's only script (inline, fetches nothing): once loaded, it records on <html> how many images
decoded, and how wide the page is against the window, so a headless browser's --dump-dom shows whether every
figure displayed and whether a phone must scroll the page sideways (tests/ground/test_report_browser.py)."""

_SURFACE_TEXT = {
    "local-linear": "The surface is estimated from the remaining points: each point is weighted by its measurement "
                    "noise from the sensor model in the log header, points their neighbours contradict beyond that "
                    "noise are left out, and each occupied grid cell's height is a local plane fitted over the widest "
                    "neighbourhood the noise allows; a piecewise-cubic Clough-Tocher surface through those heights, "
                    "kept within each triangle's data, is evaluated on a regular grid; ",
    "cubic-limited": "A piecewise-cubic Clough-Tocher surface, kept within each triangle's data, is fitted to the "
                     "remaining points over their Delaunay triangulation and evaluated on a regular grid; ",
    "cubic": "A piecewise-cubic Clough-Tocher surface is fitted to the remaining points over their Delaunay "
             "triangulation and evaluated on a regular grid; ",
    "linear": "A piecewise-planar surface is fitted to the remaining points over their Delaunay triangulation and "
              "evaluated on a regular grid; ",
}


_SLOPES_TEXT = {
    "gp": "its slopes there taken through the heights a Gaussian process fitted to them and their noise predicts",
    "gp-bridges": "where it spans further than the smoothing reached, its slopes taken through the heights a Gaussian "
                  "process fitted to them and their noise predicts",
}
"""Where the local-linear surface's cubic took its slopes, by `--surface-slopes` value, when not scipy's."""


def method_text(surface_fit: str | None = None, surface_slopes: str | None = None, noise_corrections: bool = False,
                pointing_bias: bool = False, surface_limit: str | None = None) -> str:
    """The method paragraph of the report, naming the surface fit the report used (`ground.surface`), where its
    cubic took its slopes when not scipy's (`ground.gp_slopes`), what it did where it would leave a triangle's data
    (`ground.smoothing.CubicLimit`), and the noise corrections asked for (`ground.report.ReportOptions`)."""
    surface = _SURFACE_TEXT.get(str(surface_fit), "A surface is fitted to the remaining points and evaluated on a "
                                                  "regular grid; ")  # a report that does not say which
    slopes = _SLOPES_TEXT.get(str(surface_slopes))
    if surface_fit == "local-linear" and slopes is not None:
        surface = surface.replace("through those heights, kept", f"through those heights ({slopes}), kept")
    if surface_limit == "linear":
        surface = surface.replace("kept within each triangle's data", "kept within each triangle's data (planar "
                                  "through the triangle's corners where the cubic would leave them)")
    if noise_corrections:
        surface += ("with the noise corrections asked for, each point is weighed by the noise its neighbours' range "
                    "gives and each smoothing window is refitted as a quadratic where it agrees with the narrower "
                    "ones; ")
    if pointing_bias:
        surface += ("the points were first moved back along their beams by what the stated pointing error puts them "
                    "behind the surface; ")
    return (
        "Each LiDAR range sample is turned into a point in the storage frame from the drone position "
        "and attitude and the servo angle of the swept beam (eqs. 3-6 of Alsayed & Nabawy, Drones 2022, "
        "6, 386). Returns from the walls and the roof are removed using the known storage dimensions, "
        "leaving the floor and the stockpile. " + surface + "the volume "
        "is the sum over grid cells of surface height times cell area (eq. 7). Cells outside the "
        "surface's extent have no surface and are treated by the empty-cell policy above. When a reference "
        "volume is known, the volume error Ve is the absolute difference between the measured and the "
        "true volume as a percentage of the true volume (eq. 8). The area coverage ratio R_a is the "
        "projected area of the fitted surface as a percentage of the storage floor area (eq. 9). The 90 % "
        "interval is the range that holds the true volume in 9 surveys of 10: its width adds up, in quadrature, "
        "what the flight could not settle (ground never seen, gaps between sweep tracks, the sensor's noise, the "
        "pose's drift, a base's own error), each scaled by a factor calibrated on simulated surveys with known "
        "volumes; the verdict names the errors that hold most of it."
    )


METHOD_TEXT = method_text()
"""The method paragraph of a report that does not name its surface fit."""

_IMAGE_MIME: dict[str, str] = {
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
    ".svg": "image/svg+xml",
}

ENGINEER_HEADING = "Engineer's details"
ENGINEER_NOTE = ("The survey's processing figures, the configuration the payload flew with and how the volume was "
                 "computed.")
"""Under the heading in the HTML and the PDF; the Markdown, which has no heading there, leads with its words."""

_MAX_INLINE_LIST = 12
"""Longer lists/arrays are summarised by length in "All figures" instead of printed."""


# ------------------------------------------------------------------------------------ number format


def _is_missing(v: Any) -> bool:
    return v is None


def _finite_real(v: Any) -> float | None:
    """The value as a finite float, or None when it is not a real number (or NaN/inf)."""
    if isinstance(v, bool | np.bool_) or not isinstance(v, numbers.Real):
        return None
    f = float(v)
    return f if math.isfinite(f) else None


def fmt_value(v: Any) -> str:
    """Generic formatting for values without a known unit: ints with separators, floats to 6 digits."""
    if _is_missing(v):
        return UNKNOWN
    if isinstance(v, bool | np.bool_):
        return "yes" if v else "no"
    if isinstance(v, numbers.Integral):
        return f"{int(v):,d}"
    if isinstance(v, numbers.Real):
        f = float(v)
        return f"{f:,.6g}" if math.isfinite(f) else str(f)
    if isinstance(v, str | Path):
        return str(v)
    if isinstance(v, np.ndarray):
        if v.size > _MAX_INLINE_LIST:
            return f"array {v.dtype} shape {v.shape}"
        return "[" + ", ".join(fmt_value(x) for x in v.ravel().tolist()) + "]"
    if isinstance(v, list | tuple | set | frozenset):
        items = list(v)
        if len(items) > _MAX_INLINE_LIST:
            return f"[{len(items):,} items]"
        return "[" + ", ".join(fmt_value(x) for x in items) + "]"
    return str(v)


def signless_zero(v: float, spec: str) -> float:
    """v, or +0.0 when it shows as zero in the format spec ('.1f', '+12,.1f'): -0.04 m³ shown as '-0.0' reads as a
    negative volume to a surveyor; the sign of what lies below the last digit shown is noise."""
    digits = spec.rpartition(".")[2].rstrip("f%")
    if spec.endswith(("f", "%")) and digits.isdigit():
        scale = 100.0 if spec.endswith("%") else 1.0
        if round(v * scale, int(digits)) == 0.0:
            return 0.0
    return v


def _fmt_number(v: Any, spec: str, unit: str = "") -> str:
    """Format a real number with `spec` and unit; None -> unknown; anything else generically."""
    if _is_missing(v):
        return UNKNOWN
    f = _finite_real(v)
    if f is None:
        return fmt_value(v)
    return f"{signless_zero(f, spec):{spec}}{unit}"


def fmt_volume(v: Any) -> str:
    return _fmt_number(v, ",.1f", " m³")


def fmt_pct(v: Any) -> str:
    return _fmt_number(v, ".2f", " %")


def fmt_count(v: Any) -> str:
    if _is_missing(v):
        return UNKNOWN
    f = _finite_real(v)
    if f is None or f != int(f):
        return fmt_value(v)
    return f"{int(f):,d}"


_SUMMARY_SUBKEYS: dict[str, tuple[str, ...]] = {
    "storage": ("length_m", "width_m", "height_m"),
    "site": ("lat_deg", "lon_deg", "alt_m", "heading_deg"),
    "log": ("blocks_ok", "blocks_corrupt", "blocks_truncated", "closed_cleanly"),
}
"""Sub-keys a summary cell shows; any others of the same dict go to "All figures"."""


def _fmt_storage(v: Any) -> str:
    if not isinstance(v, Mapping):
        return fmt_value(v)
    dims = [_fmt_number(v.get(k), ".2f", " m") for k in _SUMMARY_SUBKEYS["storage"]]
    return " × ".join(dims)


def _fmt_site(v: Any) -> str:
    """Where the building stands: its corner (deg, deg, m above sea level) and its x axis' heading."""
    if _is_missing(v):
        return UNKNOWN
    if not isinstance(v, Mapping):
        return fmt_value(v)
    return (f"{_fmt_number(v.get('lat_deg'), '.7f', '°')}, {_fmt_number(v.get('lon_deg'), '.7f', '°')}, "
            f"{_fmt_number(v.get('alt_m'), '.2f', ' m')} MSL; {_fmt_number(v.get('heading_deg'), '.2f', '°')} "
            "from north")


def _fmt_log(v: Any) -> str:
    if not isinstance(v, Mapping):
        return fmt_value(v)
    parts = [f"{fmt_count(v.get(k))} {name}" for k, name in
             (("blocks_ok", "ok"), ("blocks_corrupt", "corrupt"), ("blocks_truncated", "truncated"))]
    closed = {True: "; closed by its writer", False: "; not closed: cut short (see the warnings)"}
    state = v.get("closed_cleanly")
    return ", ".join(parts) + (closed[state] if isinstance(state, bool) else "")


def headline(report: Mapping[str, Any]) -> str:
    """'Stockpile volume: V (90 % interval a – b)' in the report's display unit, with m³ beside another unit; over
    an earlier survey 'Change since the earlier survey: ...', over a fitted floor '... over the fitted floor: ...'."""
    from ground.piles import VolumeUnit
    v, iv = report.get("volume_m3"), report.get("volume_interval_m3")
    base = report.get("base") if isinstance(report.get("base"), Mapping) else {}
    label = {"survey": "Change since the earlier survey", "fitted-floor": "Stockpile volume over the fitted floor"
             }.get(str(base.get("kind")), "Stockpile volume")
    text = f"{label}: {fmt_volume(v)}" + (
        "" if fmt_interval(iv) == UNKNOWN else f" (90 % interval {fmt_interval(iv)})")
    try:
        unit = VolumeUnit(report.get("volume_unit", VolumeUnit.M3.value))
    except ValueError:
        return text
    if unit is VolumeUnit.M3 or fmt_volume(v) == UNKNOWN:
        return text
    shown = f"{label}: {unit.of_m3(float(v)):,.1f} {unit.symbol}"
    if fmt_interval(iv) != UNKNOWN:
        shown += f" (90 % interval {unit.of_m3(float(iv[0])):,.1f} – {unit.of_m3(float(iv[1])):,.1f} {unit.symbol})"
    return f"{shown}; {text.removeprefix(label + ': ')}"


def reach_phrase(echo: Mapping[str, Any]) -> str:
    """What report.json's `echo` says the rangefinder reaches (`ground.echo_reach`): "the LIDAR's reach (about 23 m at
    normal incidence on 30 % reflective ground, the return model's assumption; less at a slant)", or for a simulated
    sensor without a return model, its range at any incidence."""
    reach = math.floor(float(echo["reach_at_normal_incidence_m"]))
    if echo.get("target_reflectance") is None:
        return f"the simulated {echo['sensor']}'s range ({reach:d} m at any incidence)"
    return (f"the {echo['sensor']}'s reach (about {reach:d} m at normal incidence on "
            f"{100.0 * float(echo['target_reflectance']):.0f} % reflective ground, the return model's assumption; "
            "less at a slant)")


def fmt_echo(v: Any) -> str:
    """report.json's `echo` (`ground.echo_reach.echo_record`) as one line: how many samples had no echo, and how many
    of those aimed beyond the rangefinder's reach (unknown when absent or malformed)."""
    try:
        aimed, none = int(v["samples_aimed"]), int(v["no_echo"])
        line = f"{none:,} of {aimed:,} samples without an echo ({100.0 * none / aimed if aimed else 0.0:.1f} %)"
        if none:
            line += f"; {int(v['beyond_reach']):,} of them aimed beyond {reach_phrase(v)}"
        return line
    except (TypeError, KeyError, ValueError, OverflowError):
        return UNKNOWN


def fmt_interval(v: Any) -> str:
    """[low, high] m³ as 'low – high m³' (unknown when absent or malformed)."""
    if not (isinstance(v, list | tuple) and len(v) == 2):
        return UNKNOWN
    lo, hi = (fmt_volume(x) for x in v)
    return UNKNOWN if UNKNOWN in (lo, hi) else f"{lo.removesuffix(' m³')} – {hi}"


_SUMMARY_FORMAT = {
    "volume_m3": fmt_volume,
    "volume_interval_m3": fmt_interval,
    "base": lambda v: fmt_value(v.get("description")) if isinstance(v, Mapping) else fmt_value(v),
    "true_volume_m3": fmt_volume,
    "volume_error_pct": fmt_pct,
    "coverage_ratio_pct": fmt_pct,
    "bridged_area_m2": lambda v: _fmt_number(v, ",.0f", " m²"),
    "n_samples": fmt_count,
    "n_points_used": fmt_count,
    "n_points_removed_walls": fmt_count,
    "echo": fmt_echo,
    "cell_size_m": lambda v: _fmt_number(v, ".3f", " m"),
    "empty_cell_policy": fmt_value,
    "sensor_noise": fmt_value,
    "pose_source": fmt_value,
    "storage": _fmt_storage,
    "site": _fmt_site,
    "log": _fmt_log,
    "source": fmt_value,
    "software_version": fmt_value,
    "elapsed_s": lambda v: _fmt_number(v, ",.2f", " s"),
}


def flatten(d: Mapping[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    """Nested mappings -> [(dotted.name, leaf value)], in insertion order."""
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        name = f"{prefix}.{k}" if prefix else str(k)
        if isinstance(v, Mapping) and len(v) > 0:
            out.extend(flatten(v, name))
        else:
            out.append((name, "{}" if isinstance(v, Mapping) else v))
    return out


# ------------------------------------------------------------------------------------ content model


@dataclass
class ReportContent:
    """Everything both renderers print, already formatted as plain (unescaped) strings."""

    headline: str
    warnings: list[str]
    summary: list[tuple[str, str]]
    images: list[tuple[str, Path]] = field(default_factory=list)
    method: str = METHOD_TEXT
    extra: list[tuple[str, str]] = field(default_factory=list)
    config: list[tuple[str, str]] = field(default_factory=list)
    config_file: str | None = None
    verdict: str | None = None
    to_narrow: list[str] = field(default_factory=list)  # ground.metadata.remedies: under the verdict
    metadata: list[tuple[str, str]] = field(default_factory=list)  # ground.metadata.metadata_rows
    piles: tuple[list[str], list[list[str]]] = ([], [])  # ground.piles.pile_rows: header, rows
    piles_method: str | None = None
    piles_note: str | None = None  # ground.piles.piles_note: the table reconciled with the survey, under it
    page_images: list[tuple[str, Path]] = field(default_factory=list)  # PAGE_IMAGES, under the pile table


def _config_value(v: Any) -> str:
    """A configuration value as the file writes it (1480, not "1,480": a pulse width is not a count)."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, numbers.Real):
        return f"{float(v):.12g}" if isinstance(v, float) else str(v)
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_config_value(x) for x in v) + "]"
    return UNKNOWN if v is None else str(v)


MIN_WARNING_CLAUSES = 3
"""A warning of this many clauses or more (joined by "; ", as the pose correction's statement is) is shown as its first
clause with the others listed under it: a paragraph of a dozen findings is what a reader skips."""


def warning_parts(text: str) -> tuple[str, list[str]]:
    """A warning's headline and its further clauses: split at the "; " outside any parentheses when it has at least
    MIN_WARNING_CLAUSES of them, else the whole text and none."""
    clauses, depth, start = [], 0, 0
    for i, ch in enumerate(text):
        depth += (ch == "(") - (ch == ")")
        if depth == 0 and text.startswith("; ", i):
            clauses.append(text[start:i])
            start = i + 2
    clauses.append(text[start:])
    if len(clauses) < MIN_WARNING_CLAUSES:
        return text, []
    return clauses[0], clauses[1:]


def _html_warning(text: str) -> str:
    head, more = warning_parts(text)
    return f"<li>{_e(head)}" + ("<ul>" + "".join(f"<li>{_e(m)}</li>" for m in more) + "</ul>" if more else "") + "</li>"


def _texts(value: Any) -> list[str]:
    """A report.json list of sentences as strings, whatever a hand-edited file holds there (None: none; one string:
    one sentence, not its characters)."""
    if value is None:
        return []
    if isinstance(value, str):
        return [value]
    if isinstance(value, Iterable):
        return [str(x) for x in value]
    return [str(value)]


def _warnings(report: Mapping[str, Any]) -> list[str]:
    return _texts(report.get("warnings"))


def _image_caption(name: str) -> str:
    return _IMAGE_CAPTIONS.get(name, name.replace("_", " ").strip().capitalize() or "Figure")


def build_content(report: Mapping[str, Any], images: ImageMap | None) -> ReportContent:
    """Format the report once, for both Markdown and HTML."""
    from ground.metadata import metadata_rows
    from ground.piles import pile_rows, piles_note
    no_reference = report.get("true_volume_m3") is None  # a real survey: no "True volume: unknown" rows
    summary = [(_SUMMARY_LABELS[k], _SUMMARY_FORMAT[k](report.get(k))) for k in SUMMARY_KEYS
               if not (no_reference and k in REFERENCE_KEYS) and not (k in OPTIONAL_KEYS and report.get(k) is None)]
    handled = {*SUMMARY_KEYS, "warnings", "config", "metadata", "piles", "verdict", "to_narrow_interval"}
    if no_reference:
        handled |= {"volume_error_m3", "volume_error_pct", "truth_in_interval"}
    extra_items: dict[str, Any] = {}
    for key, shown in _SUMMARY_SUBKEYS.items():  # e.g. log.bytes_skipped: not in the summary cell
        sub = report.get(key)
        if isinstance(sub, Mapping):
            extra_items.update({f"{key}.{k}": v for k, v in sub.items() if k not in shown})
    extra_items.update({k: v for k, v in report.items() if k not in handled})
    # a null in report.json is a figure this survey has none of (no other reading, no second flight), not one lost
    extra = [(name, NOT_APPLICABLE if v is None else fmt_value(v)) for name, v in flatten(extra_items)]
    cfg = report.get("config")
    config_rows, config_file = [], None
    if isinstance(cfg, Mapping):
        config_file = None if cfg.get("file") is None else str(cfg.get("file"))
        config_rows = [(name, _config_value(v)) for name, v in flatten({k: v for k, v in cfg.items() if k != "file"})]
    elif cfg is not None:
        config_rows = [("config", _config_value(cfg))]
    piles = report.get("piles")
    metadata = metadata_rows(report.get("metadata"))
    if metadata and report.get("software_version") is not None:
        metadata.append(("Report software", str(report["software_version"])))
    return ReportContent(
        verdict=None if report.get("verdict") is None else str(report.get("verdict")),
        to_narrow=_texts(report.get("to_narrow_interval")),
        metadata=metadata, piles=pile_rows(piles),
        piles_method=str(piles.get("method")) if isinstance(piles, Mapping) and piles.get("method") else None,
        piles_note=piles_note(piles),
        config=config_rows, config_file=config_file,
        method=method_text(report.get("surface_fit"), report.get("surface_slopes"),
                           report.get("noise_corrections") is True, report.get("pointing_bias") is True,
                           report.get("surface_limit")),
        headline=headline(report),
        warnings=_warnings(report),
        summary=summary,
        images=[(_image_caption(str(n)), Path(p)) for n, p in (images or {}).items() if n not in PAGE_IMAGES],
        page_images=[(_image_caption(n), Path(images[n])) for n in PAGE_IMAGES if n in (images or {})],
        extra=extra,
    )


# ------------------------------------------------------------------------------------------ markdown


def _md_text(s: str) -> str:
    """Neutralise characters that would become HTML or break a table row when a viewer renders."""
    s = s.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")
    return " ".join(s.replace("|", "\\|").splitlines())


def _md_table(header: tuple[str, str], rows: list[tuple[str, str]]) -> list[str]:
    lines = [f"| {header[0]} | {header[1]} |", "|---|---|"]
    lines += [f"| {_md_text(k)} | {_md_text(v)} |" for k, v in rows]
    return lines


def config_note(content: ReportContent) -> str:
    """Where the payload's configuration came from (its log header's ``config`` record)."""
    src = (f"the configuration file {content.config_file} with the command line's flags over it"
           if content.config_file else "no configuration file: its command line's flags and built-in defaults")
    return f"What the payload ran with, from its log header: {src} (keys as in docs/configuration.md)."


def _relative_ref(image: Path, out_dir: Path) -> str:
    """Image reference relative to the report, URL-quoted (spaces etc.), POSIX separators."""
    try:
        rel = os.path.relpath(image.resolve(), out_dir.resolve())
    except ValueError:  # different drive on Windows
        rel = image.name
    return quote(Path(rel).as_posix())


def _md_figures(images: list[tuple[str, Path]], out_dir: Path, level: str) -> list[str]:
    lines = []
    for caption, path in images:
        alt = _md_text(caption).replace("[", "\\[").replace("]", "\\]")
        lines += ["", f"{level} {_md_text(caption)}", "", f"![{alt}]({_relative_ref(path, out_dir)})"]
        if not path.is_file():
            lines += ["", f"*Image not found: {_md_text(path.name)}*"]
    return lines


def render_markdown(content: ReportContent, out_dir: Path) -> str:
    """The report.md text, in the page's order (`render_html`); image links are relative to `out_dir`."""
    lines = [f"# {REPORT_TITLE}", ""]
    if content.metadata:
        lines += [*_md_table(("Survey", ""), content.metadata), ""]
    lines += [f"**{_md_text(content.headline)}**", ""]
    if content.verdict:
        lines += [f"Verdict: {_md_text(content.verdict)}", ""]
    if content.to_narrow:
        lines += [f"To narrow the interval: {_md_text('; '.join(content.to_narrow))}", ""]
    head, rows = content.piles
    if rows:
        lines += ["## Piles", "", f"Found as {_md_text(content.piles_method or 'connected regions')}.", ""]
        lines += ["| " + " | ".join(_md_text(h) for h in head) + " |", "|" + "---|" * len(head)]
        lines += ["| " + " | ".join(_md_text(c) for c in r) + " |" for r in rows] + [""]
        lines += [_md_text(content.piles_note), ""] if content.piles_note else []
    lines += ["## Warnings", ""]
    if content.warnings:
        n = len(content.warnings)
        lines += [f"> **⚠ {n} warning{'s' if n != 1 else ''}: read before using the volume.**", ">"]
        for w in content.warnings:
            head, more = warning_parts(w)
            lines += [f"> - {_md_text(head)}", *(f">   - {_md_text(m)}" for m in more)]
    else:
        lines += ["No warnings."]
    if content.page_images:
        lines += ["", "## Map, 3D view and cross-sections", *_md_figures(content.page_images, out_dir, "###"), ""]
    note = f"{ENGINEER_HEADING}: {ENGINEER_NOTE[0].lower()}{ENGINEER_NOTE[1:]}"
    lines += ["", "---", "", f"*{note}*", "", "## Summary", ""]
    lines += _md_table(("Quantity", "Value"), content.summary)
    if content.images:
        lines += ["", "## Figures", *_md_figures(content.images, out_dir, "###")]
    if content.config:
        lines += ["", "## Configuration (as flown)", "", config_note(content), ""]
        lines += _md_table(("Key", "Value"), content.config)
    lines += ["", "## Method", "", content.method]
    if content.extra:
        lines += ["", "## All figures", ""]
        lines += _md_table(("Name", "Value"), content.extra)
    return "\n".join(lines) + "\n"


def write_markdown(report: Mapping[str, Any], images: ImageMap | None, out_path: str | Path) -> Path:
    """Write the human-readable report.md; images are referenced by path relative to it."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_markdown(build_content(report, images), out.parent), encoding="utf-8")
    return out


# ---------------------------------------------------------------------------------------------- html

_CSS = """
body { font-family: system-ui, -apple-system, "Segoe UI", Roboto, Helvetica, Arial, sans-serif;
       max-width: 60rem; margin: 2rem auto; padding: 0 1rem; color: #1b1b1b; line-height: 1.45; }
h1 { border-bottom: 2px solid #444; padding-bottom: .3rem; }
.headline { font-size: 1.4rem; font-weight: 600; }
.warnings { background: #fff3cd; border: 2px solid #d39e00; border-left-width: .6rem;
            padding: .6rem 1rem; border-radius: .3rem; color: #5c4300; }
.warnings h2 { margin-top: .2rem; color: #8a5a00; }
.ok { color: #2d6a2d; }
table { border-collapse: collapse; margin: .5rem 0 1rem; }
th, td { border: 1px solid #bbb; padding: .25rem .6rem; text-align: left; vertical-align: top; }
th { background: #eee; }
td.num { font-variant-numeric: tabular-nums; }
figure { margin: 1rem 0; }
figure img { max-width: 100%; height: auto; border: 1px solid #ddd; }
figcaption { font-size: .9rem; color: #555; }
.missing { color: #a00; font-style: italic; }
.title-block h1 { margin-bottom: .4rem; }
table.meta th { background: none; border: none; padding: .1rem .8rem .1rem 0; font-weight: 600; }
table.meta td { border: none; padding: .1rem 0; overflow-wrap: anywhere; }
.verdict { font-size: 1.1rem; }
.engineer { margin-top: 2.5rem; border-top: 2px solid #444; }
.wide { overflow-x: auto; max-width: 100%; }
.wide table { margin-top: 0; }
td { overflow-wrap: anywhere; }
@media print {
  figure, .warnings, tr { break-inside: avoid; }
  h2, h3 { break-after: avoid; }
  thead { display: table-header-group; }
  body { max-width: none; margin: 0; }
  .wide { overflow: visible; }
  table.piles { font-size: .8rem; }
}
"""


def _e(s: str) -> str:
    return html.escape(s, quote=True)


def _html_table(header: tuple[str, str], rows: list[tuple[str, str]]) -> list[str]:
    """A two-column table in a box of its own width (a phone scrolls the table, not the page); its header row in
    <thead>, which a printed page repeats."""
    out = ['<div class="wide"><table>', f"<thead><tr><th>{_e(header[0])}</th><th>{_e(header[1])}</th></tr></thead>"]
    out += [f'<tr><td>{_e(k)}</td><td class="num">{_e(v)}</td></tr>' for k, v in rows]
    out.append("</table></div>")
    return out


def _data_uri(path: Path) -> str | None:
    """base64 data URI for an image file, or None if it cannot be read."""
    try:
        data = path.read_bytes()
    except OSError:
        return None
    mime = _IMAGE_MIME.get(path.suffix.lower(), "image/png")
    return f"data:{mime};base64,{base64.b64encode(data).decode('ascii')}"


def _html_figures(images: list[tuple[str, Path]]) -> list[str]:
    parts = []
    for caption, path in images:
        uri = _data_uri(path)
        if uri is None:
            parts.append(f'<p class="missing">Image not found: {_e(caption)} ({_e(path.name)})</p>')
        else:
            parts.append(f'<figure><img alt="{_e(caption)}" src="{uri}">'
                         f"<figcaption>{_e(caption)}</figcaption></figure>")
    return parts


def render_html(content: ReportContent) -> str:
    """The self-contained report.html text (inline CSS, inlined images, nothing fetched), in the order a
    customer reads: who/where/when, the volume and verdict, the piles, the warnings, the map, 3D view and
    sections; then the engineer's details."""
    parts = [
        "<!DOCTYPE html>",
        '<html lang="en">',
        "<head>",
        '<meta charset="utf-8">',
        '<meta name="viewport" content="width=device-width, initial-scale=1">',
        f"<title>{_e(REPORT_TITLE)}</title>",
        f"<style>{_CSS}</style>",
        "</head>",
        "<body>",
        '<header class="title-block">',
        f"<h1>{_e(REPORT_TITLE)}</h1>",
    ]
    if content.metadata:
        parts += ['<table class="meta">']
        parts += [f"<tr><th>{_e(k)}</th><td>{_e(v)}</td></tr>" for k, v in content.metadata]
        parts.append("</table>")
    parts.append("</header>")
    parts.append(f'<p class="headline" id="volume">{_e(content.headline)}</p>')
    if content.verdict:
        parts.append(f'<p class="verdict" id="verdict"><strong>Verdict:</strong> {_e(content.verdict)}</p>')
    if content.to_narrow:
        parts.append(f'<p class="narrow" id="to-narrow"><strong>To narrow the interval:</strong> '
                     f'{_e("; ".join(content.to_narrow))}</p>')
    head, rows = content.piles
    if rows:
        parts += ["<h2>Piles</h2>", f"<p>Found as {_e(content.piles_method or 'connected regions')}.</p>",
                  '<div class="wide"><table class="piles" id="piles">',
                  "<thead><tr>" + "".join(f"<th>{_e(h)}</th>" for h in head) + "</tr></thead>"]
        parts += ["<tr>" + "".join(f'<td class="num">{_e(c)}</td>' for c in r) + "</tr>" for r in rows]
        parts.append("</table></div>")
        if content.piles_note:
            parts.append(f'<p class="piles-note" id="piles-note">{_e(content.piles_note)}</p>')
    parts += _html_warnings(content)
    if content.page_images:
        parts += ["<h2>Map, 3D view and cross-sections</h2>", *_html_figures(content.page_images)]
    parts += ['<section class="engineer">', f"<h2>{_e(ENGINEER_HEADING)}</h2>", f"<p>{_e(ENGINEER_NOTE)}</p>",
              "<h3>Summary</h3>", *_html_table(("Quantity", "Value"), content.summary)]
    if content.images:
        parts += ["<h3>Figures</h3>", *_html_figures(content.images)]
    if content.config:
        parts += ["<h3>Configuration (as flown)</h3>", f"<p>{_e(config_note(content))}</p>"]
        parts += _html_table(("Key", "Value"), content.config)
    parts += ["<h3>Method</h3>", f"<p>{_e(content.method)}</p>"]
    if content.extra:
        parts += ["<h3>All figures</h3>", *_html_table(("Name", "Value"), content.extra)]
    parts += ["</section>", f"<script>{IMAGE_CHECK_SCRIPT}</script>", "</body>", "</html>"]
    return "\n".join(parts) + "\n"


def _html_warnings(content: ReportContent) -> list[str]:
    """The warnings box, under the volume and the piles and before the figures: what the verdict asks the reader to
    read comes before what it qualifies."""
    parts: list[str] = []
    if content.warnings:
        n = len(content.warnings)
        parts += [
            '<section class="warnings" role="alert">',
            f"<h2>⚠ Warnings ({n}): read before using the volume</h2>",
            "<ul>",
            *(_html_warning(w) for w in content.warnings),
            "</ul>",
            "</section>",
        ]
    else:
        parts += ["<h2>Warnings</h2>", '<p class="ok">No warnings.</p>']
    return parts


def write_html(report: Mapping[str, Any], images: ImageMap | None, out_path: str | Path) -> Path:
    """Write report.html: one self-contained file with the same content as report.md."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text(render_html(build_content(report, images)), encoding="utf-8")
    return out


# ----------------------------------------------------------------------------------------------- ply

_PLY_COLOR_CMAP = "viridis"


def height_colors(z: np.ndarray, cmap: str = _PLY_COLOR_CMAP) -> np.ndarray:
    """(N, 4) uint8 RGBA for heights z, min..max mapped over the colormap (same look as the plots)."""
    from matplotlib import colormaps

    z = np.asarray(z, dtype=float)
    if z.size == 0:
        return np.empty((0, 4), dtype=np.uint8)
    lo, hi = float(z.min()), float(z.max())
    t = (z - lo) / (hi - lo) if hi > lo else np.full(z.shape, 0.5)
    return colormaps[cmap](t, bytes=True)


def _empty_ply_header(with_color: bool) -> bytes:
    props = ["property float x", "property float y", "property float z"]
    if with_color:
        props += [f"property uchar {c}" for c in ("red", "green", "blue", "alpha")]
    lines = ["ply", "format binary_little_endian 1.0", "element vertex 0", *props, "end_header"]
    return ("\n".join(lines) + "\n").encode("ascii")


def write_ply(points_w: np.ndarray, out_path: str | Path, heights_as_color: bool = True) -> Path:
    """Write the cloud as binary PLY (float32 xyz, optional RGBA by height) for any 3-D viewer.

    Rows with NaN/inf are dropped: viewers choke on them and they carry no geometry. An empty
    cloud still gives a valid PLY with 0 vertices (trimesh cannot export that, so the header is
    written directly).
    """
    pts = np.asarray(points_w, dtype=float)
    if pts.size == 0:
        pts = np.empty((0, 3))
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"points_w must be (N, 3), got shape {pts.shape}")
    pts = pts[np.all(np.isfinite(pts), axis=1)]
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    if pts.shape[0] == 0:
        out.write_bytes(_empty_ply_header(heights_as_color))
        return out

    import trimesh  # heavy import, only needed here

    colors = height_colors(pts[:, 2]) if heights_as_color else None
    cloud = trimesh.PointCloud(pts, colors=colors)
    cloud.export(str(out), file_type="ply", encoding="binary")
    return out
