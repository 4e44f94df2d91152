"""`pilescan-ground`: turn a survey's sample log into a volume report (`report`), compare two surveys of one
building (`compare`), or receive the payload's live sample stream into a sample log (`listen`)."""

from __future__ import annotations

import argparse
import logging
import math
import sys
from collections.abc import Sequence

from firmware_py.core.cli import (
    ArgumentParser,
    ConfigTables,
    UserError,
    add_config_option,
    add_verbosity,
    finite_float,
    reading_input,
    run_cli,
)
from firmware_py.core.header import MAX_LEVER_ARM_M
from firmware_py.core.keys import load_key
from firmware_py.core.rundir import check_free
from firmware_py.core.storage import Storage
from firmware_py.core.surface_file import SEEN_RADIUS_M
from firmware_py.core.version import software_version
from ground import listen
from ground.base import BaseKind, BaseSpec
from ground.exports.formats import ALL as EXPORT_ALL
from ground.exports.formats import ExportFormat, parse_formats
from ground.metadata import SurveyInfo, check_timezone, metadata_rows
from ground.pile_change import format_pile_changes, pile_changes
from ground.piles import DEFAULT_MIN_PILE_AREA_M2, MassUnit, PileOptions, VolumeUnit, pile_rows, piles_note
from ground.pose_knots import PoseCorrectionOptions
from ground.render import fmt_echo, warning_parts
from ground.report import make_report
from ground.self_calibration import KnownMount
from ground.smoothing import DEFAULT_CUBIC_LIMIT, DEFAULT_NODE_SLOPES, CubicLimit, NodeSlopes
from ground.surface import (
    DEFAULT_CELL_M,
    DEFAULT_EMPTY_CELLS,
    DEFAULT_SURFACE_FIT,
    EMPTY_CELL_POLICIES,
    LIMITED_FITS,
    SURFACE_FITS,
)
from ground.survey import DEFAULT_MAX_GRID_MEMORY_BYTES, ReportOptions
from ground.volume_warnings import DEFAULT_MAX_INTERVAL_PCT

log = logging.getLogger(__name__)

CONFIG_OPTIONS: ConfigTables = {
    "report": {"site.name": "--site-name", "site.timezone": "--timezone", "survey.operator": "--operator",
               "survey.aircraft": "--aircraft"},  # and its [site] is checked against the log's building,
    # its [[piles]] name the piles (ReportOptions.site, .piles: read from the file, no option)
    "compare": {},  # no option: its [site] is checked against the log's building (ReportOptions.site)
    "listen": {"payload.signing_key": "--signing-key"},
}
"""Configuration key -> the option it sets, per subcommand (`firmware_py.core.cli.apply_config`). listen's
--stream is where the ground listens (udp:0.0.0.0:PORT), not the payload's [payload] stream address."""


def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog="pilescan-ground", description=__doc__)
    ap.add_argument("--version", action="version", version=software_version())
    add_verbosity(ap)
    add_config_option(ap)
    sub = ap.add_subparsers(dest="command", required=True, parser_class=ArgumentParser)
    r = sub.add_parser("report", help="volume report from a run directory or a sample log")
    r.add_argument("source", metavar="RUN_DIR_OR_LOG", nargs="+",
                   help="run directory (reads truth.json too) or .pslog; several: the flights of one survey (the "
                        "same building, site and sensor; e.g. a first flight and its `pilescan-sitl plan --fill-gaps` "
                        "re-flight), each log corrected on its own, their clouds merged into one report")
    r.add_argument("--out", required=True, help="report directory to write")
    r.add_argument("--force", action="store_true",
                   help="replace a report already in --out (its files are removed, report.json first)")
    r.add_argument("--truth-volume", type=finite_float, metavar="M3",
                   help="known true volume, m^3 (overrides truth.json; 0 for an empty building; with --base "
                        "RUN_OR_REPORT the true change, which may be < 0), for Ve (eq. 8)")
    r.add_argument("--max-interval-pct", type=finite_float, default=DEFAULT_MAX_INTERVAL_PCT, metavar="PCT",
                   help="warn when the volume's 90 %% interval is wider than +/-PCT %% of the volume (default "
                        f"{DEFAULT_MAX_INTERVAL_PCT:g})")
    r.add_argument("--cell", type=finite_float, default=DEFAULT_CELL_M, metavar="M",
                   help=f"grid cell side for eq. (7), m (default {DEFAULT_CELL_M})")
    r.add_argument("--empty-cells", choices=EMPTY_CELL_POLICIES, default=DEFAULT_EMPTY_CELLS,
                   help="cells outside the fitted surface: wall-strip (default: the surface carried to the "
                        "material's height where the sweeps saw it meet a wall, ground/wall_contact.py, then the "
                        "nearest height, held under the free-space ceiling; in the unseen cells a beam passed over, "
                        "where the seen surface falls towards them, its slope carried on down, to the floor at most, "
                        "ground/carry_down.py; the cells along a wall that no point reached left to that fill where "
                        "the wall contacts contradict the points' fit across them, ground/wall_strip.py), "
                        "carry-down (the same without the wall strip), "
                        "wall-contact (as carry-down, the rest copied level), nearest (extend the "
                        "surface to the walls with the nearest height), bounded (the nearest height held between the "
                        "floor and the free-space ceiling: the lowest beam that crossed above the cell, or one near it "
                        "plus 45 deg of slope, ground/unseen.py) or leave (no volume there, the paper's method)")
    r.add_argument("--base", default="floor", metavar="floor|fitted-floor|RUN_OR_REPORT",
                   help="the surface the volume is measured from: floor (the plane z = 0, default), fitted-floor (a "
                        "plane fitted to the floor the LiDAR saw: tilt and offset reported) or an earlier survey's "
                        "run or report directory (the volume is then the change since it); see ground/base.py")
    r.add_argument("--no-plots", action="store_true", help="skip the PNG figures")
    r.add_argument("--density", type=finite_float, default=None, metavar="KG_M3",
                   help="bulk density of every pile's material, kg/m^3, for its mass ([[piles]] density_kg_m3 in "
                        "the --config file wins for its pile)")
    r.add_argument("--volume-units", choices=[u.value for u in VolumeUnit], default=VolumeUnit.M3.value,
                   help="units the report shows volumes in (default m3; report.json keeps m^3 too)")
    r.add_argument("--mass-units", choices=[u.value for u in MassUnit], default=MassUnit.TONNE.value,
                   help="units the report shows masses in: t (tonnes, default) or short-ton (2,000 lb)")
    r.add_argument("--min-pile-area", type=finite_float, default=DEFAULT_MIN_PILE_AREA_M2, metavar="M2",
                   help="smallest footprint counted as a pile, m^2 (default "
                        f"{DEFAULT_MIN_PILE_AREA_M2:g}; smaller regions above the threshold are specks)")
    r.add_argument("--site-name", default=None, metavar="NAME", help="the site or building's name, for the report")
    r.add_argument("--timezone", default=None, metavar="IANA",
                   help="the site's time zone (e.g. Europe/London): the report shows local time beside UTC")
    r.add_argument("--operator", default=None, metavar="NAME", help="who flew the survey, for the report")
    r.add_argument("--aircraft", default=None, metavar="NAME", help="the aircraft flown, for the report")
    r.add_argument("--export", default=None, metavar="FORMATS",
                   help=f"also write standard exports, a comma list of {', '.join(f.value for f in ExportFormat)} "
                        f"or {EXPORT_ALL} (default: none): LAS 1.4 points, GeoTIFF surface, PLY surface mesh, GeoJSON "
                        "contours, georeferenced too when the log header has a site (docs/exports.md)")
    r.add_argument("--surface-fit", choices=SURFACE_FITS, default=DEFAULT_SURFACE_FIT,
                   help="local-linear (default: estimated from the points with their noise from the log header, "
                        "outliers left out: ground/smoothing.py), cubic-limited (the cubic through every point, kept "
                        "within each triangle's data), cubic (the paper's MATLAB 'cubicinterp') or linear")
    r.add_argument("--surface-slopes", choices=[s.value for s in NodeSlopes], default=None,
                   help="where the local-linear surface's cubic takes its slopes at the nodes: gp-bridges (default: "
                        "through the heights a Gaussian process fitted to the nodes and their noise predicts where a "
                        "triangle spans further than the smoothing windows reach, and beside it: steadier across the "
                        "gaps between sparse fan lines under pointing noise; ground/gp_slopes.py), gp (the same at "
                        "every node, about 0.5 s more) or curvature (scipy's least-curvature slopes through the node "
                        "heights as they are, about 0.2 s less)")
    r.add_argument("--surface-limit", choices=[c.value for c in CubicLimit], default=None,
                   help="where the limited cubic (local-linear, cubic-limited) would leave the range of its "
                        "triangle's three nodes (a long triangle between sparse tracks, or out to a wall contact): "
                        f"{DEFAULT_CUBIC_LIMIT.value} (default: held at that range) or linear (the plane through the "
                        "three nodes there, which keeps the lean from one to the other instead of a flat at one "
                        "corner's height; not the default: docs/design-notes.md)")
    r.add_argument("--noise-corrections", action="store_true",
                   help="take off three biases of a surface estimated from noisy points: sigmas from the neighbours' "
                        "range, windows refitted as quadratics, the wall contacts' floor test by the floor's "
                        "tolerance (not yet the default; docs/design-notes.md)")
    r.add_argument("--pointing-bias", action="store_true",
                   help="move the points back along their beams by what the header's pointing error puts them behind "
                        "the surface, and fit it again (not yet the default; ground/pointing_bias.py)")
    r.add_argument("--no-despike", action="store_true",
                   help="keep isolated one- or two-sample range spikes (default: left out, with a threshold "
                        "derived from the log header; see ground/despike.py)")
    r.add_argument("--no-servo-retiming", action="store_true",
                   help="when the two sweep directions disagree, only warn (default: re-estimate the servo's dead "
                        "time and speed from the sweeps and use them if they agree, and re-time the servo by a dead "
                        "time the floor and walls show; see ground/servo_timing.py)")
    r.add_argument("--no-self-calibration", action="store_true",
                   help="do not estimate the servo's zero and scale and the LiDAR's boresight from the floor and "
                        "walls (default: estimate them, apply those that are significant, and say so)")
    r.add_argument("--mount", type=finite_float, nargs=4, default=None,
                   metavar=("OFFSET_DEG", "SCALE_PCT", "TILT_DEG", "YAW_DEG"),
                   help="the mount's errors against the log header's calibration, as measured (on the bench after "
                        "the flight): the servo's zero offset (deg) and travel scale error (%%: +5 turns 5 %% further "
                        "per pulse than calibrated), the LiDAR's tilt out of the sweep plane and the sweep plane's "
                        "yaw (deg); applied in place of the self-calibration from the building, and said so (the "
                        "conventions report.json's self_calibration reports in; each within 20 deg or 30 %%)")
    pc = r.add_mutually_exclusive_group()
    pc.add_argument("--pose-correction", dest="pose_correction", action="store_true", default=True,
                    help="correct the logged trajectory from the building (the default): the horizontal position "
                         "and heading from the walls, the height from the floor and the pile seen at different times, "
                         "applied only when significant and said in the report (see docs/pose_error.md)")
    pc.add_argument("--no-pose-correction", dest="pose_correction", action="store_false",
                    help="take the logged trajectory as it is (a pose from motion capture or RTK, or to compare)")
    r.add_argument("--baro-walk", type=finite_float, default=PoseCorrectionOptions.vertical_walk_m_per_sqrt_s,
                   metavar="M_PER_SQRT_S",
                   help="how fast the autopilot's altitude reference is believed to drift, as a random walk "
                        f"(default {PoseCorrectionOptions.vertical_walk_m_per_sqrt_s:g}: a barometer indoors): how far "
                        "a floor seen only away from the walls may move the corrected height, and the interval's "
                        "level term when no floor pins the height (docs/uncertainty.md)")
    r.add_argument("--storage", metavar="LxWxH", type=_storage,
                   help="the building's length, width and height in metres (e.g. 30x20x10) in place of the log "
                        "header's, when that is wrong: the report warns when its sweeps measure the building other "
                        "than the header says, and says which it used")
    r.add_argument("--lever-arm", type=finite_float, nargs=3, default=None, metavar=("X", "Y", "Z"),
                   help="the LiDAR's position from the autopilot's origin, body frame (forward, right, down), m, in "
                        "place of the log header's, when that is wrong (as the payload's --lever-arm takes it): the "
                        "report warns when the floor it sees lies below z = 0, and names the one that would lift it")
    r.add_argument("--max-grid-memory-mb", type=finite_float, default=DEFAULT_MAX_GRID_MEMORY_BYTES / 2**20,
                   metavar="MB", help="refuse a --cell whose grid would need more memory than this (default "
                                      f"{DEFAULT_MAX_GRID_MEMORY_BYTES // 2**20} MiB)")
    add_verbosity(r, sub=True, quiet_help="no summary: print nothing but warnings and errors")
    add_config_option(r, sub=True)
    c = sub.add_parser("compare", help="change between two surveys of one building: cut/fill raster and figure, "
                                       "net, cut and fill volumes with their 90 %% intervals")
    c.add_argument("old", metavar="OLD", help="the earlier survey: a run directory or a report directory")
    c.add_argument("new", metavar="NEW", help="the later survey: a run directory or a report directory")
    c.add_argument("--out", required=True, help="directory to write compare.json, cutfill.png and cutfill.npz to")
    c.add_argument("--force", action="store_true", help="replace a comparison already in --out")
    c.add_argument("--cell", type=finite_float, default=DEFAULT_CELL_M, metavar="M",
                   help="grid cell side, m, for a run directory's surface (a report directory keeps its own; "
                        f"default {DEFAULT_CELL_M})")
    c.add_argument("--true-change", type=finite_float, default=None, metavar="M3",
                   help="the known net change, m^3 (a simulation's), to check the net against")
    add_verbosity(c, sub=True, quiet_help="print nothing but warnings and errors")
    add_config_option(c, sub=True)
    ls = sub.add_parser("listen", help="receive the payload's live sample stream (pilescan-payload --stream) "
                                       "into a sample log, with a status line and a summary")
    ls.add_argument("--stream", required=True, metavar="udp:HOST:PORT",
                    help="where to listen: the address the payload's --stream sends to (udp:0.0.0.0:PORT: "
                         "every interface)")
    ls.add_argument("--signing-key", default=None, metavar="FILE",
                    help="the payload's key file (64 hex digits or a passphrase line; chmod 600): take only "
                         "authenticated, fresh datagrams; unauthenticated, forged and replayed ones are refused "
                         "and counted")
    ls.add_argument("--allow-peer", action="append", default=None, metavar="HOST[:PORT]",
                    help="take datagrams only from this sender (repeatable; without a port: any port of HOST)")
    ls.add_argument("--out", default=None, metavar="FILE.pslog",
                    help="sample log to write the records to (default: count them only)")
    ls.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    ls.add_argument("--header", default=None, metavar="FILE",
                    help="log header to write: a sample log's (.pslog) or a JSON object; it carries the "
                         "storage and sensor geometry the report needs (default: a minimal header, which "
                         "`report` refuses)")
    ls.add_argument("--duration", type=finite_float, default=None, metavar="S",
                    help="stop after S seconds (default: until Ctrl-C / SIGTERM)")
    ls.add_argument("--max-log-mb", type=finite_float, default=None, metavar="MIB",
                    help=f"size cap of --out in MiB (default {listen.DEFAULT_MAX_LOG_MIB}); past it, records are "
                         "counted, not written, and one line says so")
    ls.add_argument("--web", default=None, metavar="HOST:PORT",
                    help="also serve a live page there (coverage map, track, running volume with its interval, "
                         "unseen cells, these counters; updated once a second; needs --header for the building). "
                         "It has no login: bind it to 127.0.0.1 unless the network is yours (docs/live.md)")
    add_verbosity(ls, sub=True, quiet_help="no status line or summary: print nothing but errors")
    add_config_option(ls, sub=True)
    return ap


def format_summary(rep: dict) -> str:
    """The console summary: one label column for every row; volumes in the report's display unit (with m³
    beside them when that is another unit)."""
    def pct(v):
        return "unknown" if v is None else f"{v:.2f} %"
    try:
        unit = VolumeUnit(rep.get("volume_unit", VolumeUnit.M3.value))
    except ValueError:
        unit = VolumeUnit.M3

    def vol(*v_m3: float) -> str:
        shown = " to ".join(f"{unit.of_m3(v):,.1f}" for v in v_m3) + f" {unit.symbol}"  # "-" reads as a minus
        return shown if unit is VolumeUnit.M3 else shown + " (" + " to ".join(f"{v:,.1f}" for v in v_m3) + " m³)"
    truth = rep.get("true_volume_m3")
    iv = rep.get("volume_interval_m3")
    rows = [("volume", vol(rep["volume_m3"])),
            ("90 % interval", "not estimated" if iv is None else vol(iv[0], iv[1])),
            ("base", (rep.get("base") or {}).get("description", "the floor plane z = 0"))]
    rows += [("verdict", rep["verdict"])] if rep.get("verdict") else []
    rows += [("to narrow it", "; ".join(rep["to_narrow_interval"]))] if rep.get("to_narrow_interval") else []
    if truth is not None:  # a reference volume: a simulated survey or --truth-volume
        rows += [("truth", vol(truth)), ("Ve (eq. 8)", pct(rep.get("volume_error_pct")))]
    bridged = rep.get("bridged_area_m2")
    rows += [("R_a (eq. 9)", pct(rep.get("coverage_ratio_pct")) + (
                 f" ({bridged:,.0f} m² of it with no point within {SEEN_RADIUS_M:g} m: bridged, as much a guess as "
                 "the fill)" if isinstance(bridged, float) and bridged >= 0.5 else "")),
             ("points used", f"{rep['n_points_used']:,} of {rep['n_samples']:,} samples")]
    rows += [("echoes", fmt_echo(rep["echo"]))] if rep.get("echo") else []
    if "floor_measured" in rep and not rep.get("flights"):  # a merged survey's floors are its flights' own
        rows += [("floor seen at", floor_line(rep["floor_measured"]))]
    rows += list(metadata_rows(rep.get("metadata")))
    rows += [("exports", ", ".join(rep["exports"]))] if rep.get("exports") else []
    width = max(len(label) for label, _ in rows)
    lines = [f"{label:<{width}}  {value}" for label, value in rows]
    head, piles = pile_rows(rep.get("piles"))
    if piles:
        widths = [max(len(r[i]) for r in [head, *piles]) for i in range(len(head))]
        lines += ["piles:"] + ["  " + "  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip()
                               for r in [head, *piles]]
        note = piles_note(rep.get("piles"))
        lines += [f"  {note}"] if note else []
    for w in rep.get("warnings", []):  # a warning of many clauses as the pages show it: its headline, the rest under it
        head, more = warning_parts(w)
        lines += [f"WARNING: {head}", *(f"  - {m}" for m in more)]
    return "\n".join(lines)


def floor_line(floor: dict | None) -> str:
    """report.json's `floor_measured` in words: where the lowest flat surface lies against z = 0. Above it by more than
    a few centimetres the floor is covered by material, or every height is that much high (a lever arm's z entered too
    short): the report cannot tell the two apart, the surveyor can (`ground.floor_check`). Its fall, when it has one
    (`FloorFall.laid_to_fall`): a floor laid to a fall, or material covering the floor, which again the surveyor
    tells apart."""
    if not isinstance(floor, dict) or not isinstance(floor.get("level_m"), int | float):
        return "not seen (the material hides it)"
    line = (f"{floor['level_m'] * 100:+.1f} cm from z = 0 (+/-{floor.get('std_error_m', 0.0) * 1000:.1f} mm, over "
            f"{floor.get('cover_pct', 0.0):.0f} % of the building)")
    if floor.get("laid_to_fall") and isinstance(floor.get("fall_pct"), int | float):
        towards = round(floor.get("rise_azimuth_deg", 0.0))
        line += (f", rising {floor['fall_pct']:.1f} % towards {towards:d} deg from x: a floor laid to a fall "
                 "(--base fitted-floor measures from it) or material covering the floor")
    return line


MAX_BARO_WALK_M_PER_SQRT_S = 1.0
"""The largest --baro-walk taken: 7.7 m in a minute, beyond any altitude reference that flies a survey."""


def _storage(text: str) -> Storage:
    """--storage LxWxH (argparse's type: its ValueError is the option's one-line error)."""
    try:
        return Storage.parse(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def _lever_arm(xyz: Sequence[float] | None) -> tuple[float, float, float] | None:
    """--lever-arm X Y Z, held to the payload's own limit (`firmware_py.core.header.MAX_LEVER_ARM_M`)."""
    if xyz is None:
        return None
    if any(abs(v) > MAX_LEVER_ARM_M for v in xyz):
        raise UserError(f"--lever-arm: each of X Y Z must be within +/-{MAX_LEVER_ARM_M:g} m, got "
                        f"{' '.join(f'{v:g}' for v in xyz)}")
    return (float(xyz[0]), float(xyz[1]), float(xyz[2]))


def _mount(values: Sequence[float] | None) -> KnownMount | None:
    """--mount OFFSET_DEG SCALE_PCT TILT_DEG YAW_DEG, in the code's units and held to `KnownMount`'s limits."""
    if values is None:
        return None
    offset_deg, scale_pct, tilt_deg, yaw_deg = values
    try:
        return KnownMount(math.radians(offset_deg), scale_pct / 100.0, math.radians(tilt_deg), math.radians(yaw_deg))
    except ValueError as exc:
        raise UserError(f"--mount: {exc}") from None


def _baro_walk(value: float) -> float:
    if not 0.0 < value <= MAX_BARO_WALK_M_PER_SQRT_S:
        raise UserError(f"--baro-walk must be > 0 and at most {MAX_BARO_WALK_M_PER_SQRT_S:g} m/sqrt(s), got {value:g}")
    return value


def _report(args) -> int:
    base = BaseSpec.parse(args.base)
    if args.truth_volume is not None and args.truth_volume < 0 and base.kind is not BaseKind.SURVEY:
        raise UserError(f"--truth-volume must be >= 0 m^3 (0: an empty building; < 0 only for a change since an "
                        f"earlier survey, --base RUN_OR_REPORT), got {args.truth_volume:g}")
    if not args.max_interval_pct > 0:
        raise UserError(f"--max-interval-pct must be > 0, got {args.max_interval_pct:g}")
    if args.max_grid_memory_mb <= 0:
        raise UserError(f"--max-grid-memory-mb must be > 0, got {args.max_grid_memory_mb:g}")
    if args.surface_slopes is not None and args.surface_fit != "local-linear":
        raise UserError(f"--surface-slopes {args.surface_slopes} applies to the local-linear surface fit only (the "
                        f"others interpolate the points), got --surface-fit {args.surface_fit}")
    if args.surface_limit is not None and args.surface_fit not in LIMITED_FITS:
        raise UserError(f"--surface-limit {args.surface_limit} applies to the limited cubic fits only "
                        f"({', '.join(LIMITED_FITS)}), got --surface-fit {args.surface_fit}")
    cfg = args.config_file
    for option, field_name, value in (("--density", "density_kg_m3", args.density),
                                      ("--min-pile-area", "min_area_m2", args.min_pile_area)):
        try:
            PileOptions(**{field_name: value})
        except ValueError as exc:
            raise UserError(f"{option}: {exc}") from None
    piles = PileOptions(entries=cfg.piles if cfg is not None else (), density_kg_m3=args.density,
                        min_area_m2=args.min_pile_area, volume_unit=VolumeUnit(args.volume_units),
                        mass_unit=MassUnit(args.mass_units))
    if args.timezone is not None:
        try:
            check_timezone(args.timezone)
        except ValueError as exc:
            raise UserError(f"--timezone: {exc}") from None
    info = SurveyInfo(site_name=args.site_name, timezone=args.timezone, operator=args.operator,
                      aircraft=args.aircraft)
    exports = parse_formats(args.export)
    opts = ReportOptions(cell_m=args.cell, empty_cells=args.empty_cells, plots=not args.no_plots,
                         truth_volume_m3=args.truth_volume, despike=not args.no_despike,
                         surface_fit=args.surface_fit,
                         surface_slopes=NodeSlopes(args.surface_slopes or DEFAULT_NODE_SLOPES),
                         surface_limit=CubicLimit(args.surface_limit or DEFAULT_CUBIC_LIMIT),
                         noise_corrections=args.noise_corrections, pointing_bias=args.pointing_bias,
                         servo_retiming=not args.no_servo_retiming,
                         max_grid_memory_bytes=int(args.max_grid_memory_mb * 2**20),
                         self_calibration=not args.no_self_calibration, pose_correction=args.pose_correction,
                         baro_walk_m_per_sqrt_s=_baro_walk(args.baro_walk), storage=args.storage,
                         lever_arm_m=_lever_arm(args.lever_arm), mount=_mount(args.mount),
                         max_interval_pct=args.max_interval_pct,
                         site=args.config_file.site if args.config_file is not None else None,
                         base=base, piles=piles, info=info, exports=exports)
    rep = make_report(args.source, args.out, opts, force=args.force)
    if not args.quiet:
        print(format_summary(rep))
    log.info("report written to %s (%.2f s)", args.out, rep["elapsed_s"])
    return 0


def _listen(args) -> int:
    with reading_input():  # the files it names are read (again) by config_from_args: these are input errors
        if args.signing_key is not None:
            load_key(args.signing_key)
        if args.header is not None:
            listen.load_header(args.header)
    res = listen.listen(listen.config_from_args(args), err=None if args.quiet else sys.stderr)
    if not args.quiet:
        print(listen.format_summary(res), flush=True)
    return 0


def _compare(args) -> int:
    from pathlib import Path

    import numpy as np

    from ground import compare
    from ground.report import earlier_surface, survey_source_kind
    for what, path in (("OLD", args.old), ("NEW", args.new), ("--out", args.out)):
        if not str(path).strip():
            raise UserError(f"{what} must be a non-empty path")
    for path in (args.old, args.new):
        survey_source_kind(Path(path))  # both checked before either is computed
    check_free(args.out, compare.COMPARE_FILES, force=args.force, what="compare")
    opts = ReportOptions(cell_m=args.cell, plots=False)
    old, new = earlier_surface(args.old, opts), earlier_surface(args.new, opts)
    if old.heights_m.shape == new.heights_m.shape and np.array_equal(old.heights_m, new.heights_m, equal_nan=True):
        raise UserError(f"{args.old} and {args.new} hold the same surface, cell for cell: one survey given twice? "
                        "(a change between it and itself is 0 with no uncertainty, which says nothing)")
    change = compare.compare_surfaces(old, new)
    per_pile = pile_changes(old, new, change)
    rec = compare.change_record(change, old, new, str(args.old), str(args.new), per_pile, args.true_change)
    compare.write_compare(change, rec, args.out, force=args.force)
    if not args.quiet:
        print("\n".join([compare.format_change(rec), *format_pile_changes(per_pile)]))
    return 0


def _command(args) -> int:
    return {"report": _report, "listen": _listen, "compare": _compare}[args.command](args)


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _command, config=CONFIG_OPTIONS)


if __name__ == "__main__":
    raise SystemExit(main())
