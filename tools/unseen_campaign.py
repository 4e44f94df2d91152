"""Campaign: the empty-cell policies on the piles the unseen ground decides (corner, wall-end) and the
paper's two, flown by the cached JSBSim baseline at several P_traj over the 20 servo phases.

Each survey is computed once through the ground station's batch path (`survey_from_samples`), then
filled with each policy from the same fitted surface and the same flight's free-space ceiling, so the
policies differ only in what they put into the unseen cells. Writes docs/unseen.md.

    python -m tools.unseen_campaign                      # the full campaign (a few minutes)
    python -m tools.unseen_campaign --positions 4 --out /tmp/unseen.md
"""

from __future__ import annotations

import argparse
import math
import sys
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from firmware_py.core.storage import Storage
from ground.pointcloud import SensorErrorModel, structure_mask
from ground.report import ReportOptions, contact_fit_m, pile_sigma_m, survey_from_samples
from ground.surface import (
    CONTACT_POLICIES,
    DEFAULT_CELL_M,
    DEFAULT_SURFACE_FIT,
    STRIP_POLICIES,
    Grid,
    fill_empty,
    grid_volume,
    volume_error_pct,
)
from ground.unseen import (
    Extension,
    beam_angle_sigma_rad,
    bounded_fill,
    free_space_ceilings_m,
    passed_over,
    unseen_bounds,
)
from ground.wall_contact import WallContacts, contact_fill, pin_contacts, wall_contacts
from sitl.runners.fly import FlyConfig, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.world.raycast import World
from sitl.world.stockpile import Stockpile, heightfield_mesh, paper_pile, volume_under_mesh
from tools.doc_sections import write_section
from tools.experiments import ALL_EXPERIMENTS, N_POSITIONS, _flight, servo_positions

REPOSE_SLOPE = math.tan(math.radians(35.0))
"""Flanks of the fixture piles: a typical angle of repose of bulk material (sand, gravel: 30-40 deg)."""
FIXTURE_RESOLUTION_M = 0.25
"""Vertex spacing of the fixture piles' meshes (the paper piles' spacing)."""
P_TRAJ_PCT = (20, 30)
PILES = ("corner", "wall-end", "1", "2")
FILLS = ("nearest", "wall-contact", "carry-down", "wall-strip", "nodes-everywhere", "pinned-bounded", "bounded-nearest",
         "bounded-harmonic", "bounded-biharmonic", "floor-only-biharmonic")
"""The fills compared: `nearest` (the default before issue 14 item 4); `--empty-cells wall-contact` (the default
until 2026-12-03; ground.wall_contact: the unseen cells from the surface through the points and the wall contacts);
`carry-down` (the default until 2026-12-03: the same, the rest carried down the seen slope in the unseen cells a beam
passed over: ground.carry_down); `wall-strip` (the default now: `carry-down` with the strip along each wall that no
point reached left to the fill where the wall contacts contradict the fit there, ground.wall_strip: the report's own
survey, since it changes which cells are unseen); that
surface in every cell; the contacts pinned in the unseen wall cells before `bounded`; the bounded policy with
each extension (ground.unseen), and the thin plate held by the floor alone (what the free-space ceiling adds)."""
NOISES = ("none", "appendix-a")
CELL_ERROR_FILLS = ("nearest", "wall-contact", "carry-down", "wall-strip")
"""The fills whose mean per-cell error in the unseen cells the second table states."""


def _fill(name: str, heights_fit: np.ndarray, ceiling_m: np.ndarray, contacts: WallContacts, grid: Grid,
          nodes_fit: np.ndarray, shadow: np.ndarray) -> np.ndarray:
    if name in CONTACT_POLICIES:
        return fill_empty(heights_fit, name, ceiling_m, nodes_fit, grid.cell_xy_m, shadow)
    if name == "nodes-everywhere":
        return fill_empty(nodes_fit, "nearest")
    if name == "pinned-bounded":
        return contact_fill(heights_fit, contacts, grid.x_edges, grid.y_edges, ceiling_m, Extension.NEAREST)
    if name.startswith("bounded-"):
        return bounded_fill(heights_fit, ceiling_m, Extension(name.removeprefix("bounded-")))
    if name.startswith("floor-only-"):
        return bounded_fill(heights_fit, None, Extension(name.removeprefix("floor-only-")))
    return fill_empty(heights_fit, name)


@dataclass(frozen=True)
class ConePile:
    """A pile at its angle of repose about a core on the floor: height = peak - slope x distance to the
    core segment (a point: a cone; a segment: a ridge), clipped to the floor. Placed against walls, the
    building cuts it: a core at a corner is a quarter cone, a core along an end wall a wall-end pile."""

    core_a_m: tuple[float, float]
    core_b_m: tuple[float, float]
    peak_m: float
    slope: float = REPOSE_SLOPE

    def height_m(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        a, b = np.asarray(self.core_a_m, dtype=float), np.asarray(self.core_b_m, dtype=float)
        ab = b - a
        t = np.zeros_like(x) if not ab.any() else np.clip(((x - a[0]) * ab[0] + (y - a[1]) * ab[1]) / (ab @ ab), 0, 1)
        dist = np.hypot(x - (a[0] + t * ab[0]), y - (a[1] + t * ab[1]))
        return np.clip(self.peak_m - self.slope * dist, 0.0, None)


def fixture_piles(storage: Storage) -> dict[str, ConePile]:
    """The two shapes the unseen ground decides, scaled to the building: a quarter cone in the corner at
    the origin (peak 8 m in a 15 m building, reaching 11.4 m out), and a ridge along the end wall x = 0
    whose ends stop short of both corners (the corners stay bare; its flanks face them)."""
    h = 8.0 / 15.0 * storage.height_m
    w = storage.width_m
    return {"corner": ConePile((0.0, 0.0), (0.0, 0.0), h),
            "wall-end": ConePile((0.0, 0.3 * w), (0.0, 0.7 * w), 7.0 / 8.0 * h)}


def heightfield_pile(shape: ConePile, storage: Storage, name: str) -> Stockpile:
    nx = max(2, math.ceil(storage.length_m / FIXTURE_RESOLUTION_M) + 1)
    ny = max(2, math.ceil(storage.width_m / FIXTURE_RESOLUTION_M) + 1)
    xs, ys = np.linspace(0.0, storage.length_m, nx), np.linspace(0.0, storage.width_m, ny)
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    mesh = heightfield_mesh(xs, ys, shape.height_m(gx, gy))
    return Stockpile(mesh, volume_under_mesh(mesh), f"{name} ({shape})")


def pile_named(name: str, storage: Storage) -> Stockpile:
    fixtures = fixture_piles(storage)
    return heightfield_pile(fixtures[name], storage, name) if name in fixtures else paper_pile(name, storage)


def true_heights_m(world: World, cell_m: float = DEFAULT_CELL_M) -> np.ndarray:
    """The pile's height at every cell centre of the report's grid, cast straight down from under the roof
    (`World.heights_below_m`): what a fill is scored against in the cells it had to invent."""
    cx, cy = Grid(world.storage.length_m, world.storage.width_m, cell_m).centres()
    return world.heights_below_m(np.column_stack([cx.ravel(), cy.ravel()])).reshape(cx.shape)


def run_case(pile_name: str, p_pct: float, positions: list[int], cache_dir: Path,
             policies: tuple[str, ...] = FILLS, noise_name: str = "none") -> list[dict]:
    """One row per servo phase: Ve for each policy and what the unseen cells held."""
    e = ALL_EXPERIMENTS["baseline"]
    flown = _flight(e, p_pct, cache_dir)
    base = FlyConfig(mission=e.mission(p_pct), waveform=e.waveform)
    storage = base.mission.storage
    pile = pile_named(pile_name, storage)
    world = World(storage, pile, base.lidar.max_range_m)
    t = np.arange(int(flown.duration_s * base.lidar.rate_hz) + 1) / base.lidar.rate_hz
    traj = flown.trajectory_at(t)
    truth = true_heights_m(world)
    rows = []
    for k in positions:
        cfg = replace(base, initial_position=k)
        wf = cfg.servo_waveform()
        noise = None if noise_name == "none" else SensorNoise.of(SensorNoiseModel(noise_name), cfg.lidar)
        samples = sample_flight(traj, wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame, noise=noise,
                                seed=[int(p_pct), k])
        header = log_header(replace(cfg, sensor_noise=noise.model) if noise else cfg, wf)
        # one survey with the strip rule: its heights are `wall-strip`'s column, its hull fit (the points' own fit
        # before the rule, as every other policy sees it) the surface the other fills are applied to
        sv = survey_from_samples(samples, header, storage, cfg.frame, np.array(cfg.lever_arm_body_m),
                                 ReportOptions(plots=False, empty_cells=STRIP_POLICIES[0]))
        fit = sv.heights_hull
        unseen = ~np.isfinite(fit)
        err = SensorErrorModel.from_header(header)
        t0 = time.perf_counter()
        own, ceiling = free_space_ceilings_m(sv.cloud, sv.grid, storage, err, beam_angle_sigma_rad(header),
                                             where=unseen)
        shadow = unseen & passed_over(own, storage.height_m)
        ceiling_s = time.perf_counter() - t0
        structure = structure_mask(sv.cloud, storage, err)
        contacts = wall_contacts(sv.cloud, structure, storage, err, sv.grid.cell_m)
        nodes_fit = contact_fit_m(sv.pile_points_w, pile_sigma_m(sv.cloud, structure, err), contacts, sv.grid, storage,
                                  DEFAULT_SURFACE_FIT)  # the report's contact fit, over every cell
        nodes_fit = fit if nodes_fit is None else nodes_fit  # no contacts: the points' own fit
        # the ceiling over the node fit's unseen cells too (a subset of the survey's, where it was computed)
        ceiling = np.where(np.isfinite(ceiling), ceiling, np.where(np.isfinite(nodes_fit), np.nan, storage.height_m))
        row = {"pile": pile_name, "p_traj_pct": p_pct, "noise": noise_name, "position": k, "true_m3": pile.volume_m3,
               "unseen_pct": float(unseen.mean() * 100), "ceiling_s": ceiling_s, "n_beams": len(sv.cloud.range_m),
               "n_contacts": len(contacts),
               "beam_crossed_pct": float((ceiling[unseen] < storage.height_m).mean() * 100) if unseen.any() else 0.0}
        for pol in policies:
            filled = sv.heights if pol in STRIP_POLICIES else _fill(pol, fit, ceiling, contacts, sv.grid, nodes_fit,
                                                                    shadow)
            row[f"u_{pol}_pct"] = float((filled[unseen] - truth[unseen]).sum() * sv.grid.cell_area_m2
                                        / pile.volume_m3 * 100)
            row[f"mae_{pol}_m"] = float(np.abs(filled[unseen] - truth[unseen]).mean()) if unseen.any() else 0.0
            v = grid_volume(filled, sv.grid)
            row[f"ve_{pol}_pct"] = volume_error_pct(v, pile.volume_m3)
            row[f"e_{pol}_pct"] = (v - pile.volume_m3) / pile.volume_m3 * 100
        pinned = pin_contacts(fit, contacts, sv.grid.x_edges, sv.grid.y_edges)
        at = unseen & np.isfinite(pinned)  # unseen cells holding a wall contact: the estimate against nearest's copy
        near = fill_empty(fit, "nearest")
        row["pinned_pct"] = float(at.sum() / max(1, unseen.sum()) * 100)
        row["pin_err_m"] = float(np.abs(pinned[at] - truth[at]).mean()) if at.any() else math.nan
        row["pin_nearest_err_m"] = float(np.abs(near[at] - truth[at]).mean()) if at.any() else math.nan
        held = bounded_fill(fit, ceiling, Extension.BIHARMONIC)
        at_ceiling = np.isclose(held[unseen], ceiling[unseen]) & (ceiling[unseen] < storage.height_m)
        row["held_pct"] = float(at_ceiling.mean() * 100) if unseen.any() else 0.0
        lo, hi = unseen_bounds(fit, np.where(unseen, ceiling, storage.height_m))
        row["v_lo_m3"], row["v_hi_m3"] = grid_volume(lo, sv.grid), grid_volume(hi, sv.grid)
        rows.append(row)
    return rows


def _stats(v: list[float]) -> str:
    a = np.asarray(v, dtype=float)
    return f"{a.mean():.2f} | {a.std(ddof=1) if len(a) > 1 else 0.0:.2f} | {a.max():.2f}"


def _rows_by_case(rows: list[dict]) -> list[tuple[tuple, list[dict]]]:
    keys = sorted({(r["pile"], r["p_traj_pct"], r["noise"]) for r in rows},
                  key=lambda k: (NOISES.index(k[2]), PILES.index(k[0]), k[1]))
    return [(k, [r for r in rows if (r["pile"], r["p_traj_pct"], r["noise"]) == k]) for k in keys]


TITLE = "# Unseen ground: the empty-cell policies on corner and wall-end piles"
SECTION = "unseen-campaign"
"""The page's section this campaign writes; the rest of the page (the floor out of reach, `tools.echo_check`'s section)
is other tools' and prose, kept as it is."""


def write_markdown(rows: list[dict], out: Path, policies: tuple[str, ...], command: str) -> None:
    """The campaign's tables into its section of the page (a new page: the title first)."""
    if not out.exists():
        out.write_text(TITLE + "\n", encoding="utf-8")
    write_section(out, SECTION, markdown_text(rows, policies, command))


def markdown_text(rows: list[dict], policies: tuple[str, ...], command: str) -> str:
    lines = [f"Generated by `{command}` (do not edit this section by hand).", "",
             "The paper's baseline flight (JSBSim, semi-triangular sweep, 1 m/s, 60 x 40 x 15 m building, 12 m",
             "altitude) over four piles: `corner`, a quarter cone in the corner at the origin (8 m peak, 35 deg",
             "flanks); `wall-end`, a 7 m ridge along the end wall x = 0 whose ends stop short of both corners (bare",
             "corners, flanks facing them); the paper's piles 1 and 2. Each row: the 20 servo phases (Fig. 9) through",
             "`survey_from_samples`, every fill applied to the same fitted surface and the same free-space ceiling.",
             "", "Fills: `wall-strip` (the default, `--empty-cells wall-strip`: `carry-down` with the strip along",
             "each wall that no point reached left to the fill where the wall contacts either side contradict the",
             "fit there, `ground/wall_strip.py`; its column is the report's own survey of the phase, whose unseen",
             "cells include that strip; the error columns below count every fill over the points' own unseen",
             "cells); `carry-down` (`--empty-cells carry-down`, the default until 2026-12-03: the unseen cells",
             "from the surface",
             "fitted through the pile points and the wall contacts, nodes at the walls' feet, the rest by the nearest",
             "height, but in the unseen cells a beam passed over, where the seen surface falls towards them, carried",
             "on down at its slope, to the floor at most, `ground/carry_down.py`; a wall contact,",
             "`ground/wall_contact.py`: where a sweep's lowest wall hit sits above its next beam's hit on material or",
             "floor, the material's height at the wall); `wall-contact` (`--empty-cells wall-contact`, the default",
             "until 2026-12-03: the same with the rest copied level everywhere);",
             "`nearest` (the nearest fitted",
             "cell's height, the default until this campaign); `nodes-everywhere`: the surface through the contacts",
             "in the fitted cells too; `pinned-bounded`: the fit kept, the contacts set in their unseen wall cells",
             "before `bounded` (against `bounded-nearest`: what they add as a fill alone); `bounded-<extension>`: the",
             "`bounded` policy (`ground/unseen.py`) carrying the seen surface into the unseen cells by that extension",
             "(`nearest` copy, `harmonic` membrane, `biharmonic` thin plate) held between the floor and the",
             "free-space ceiling; `floor-only-biharmonic`: the thin plate held by the floor alone (what the ceiling",
             "adds). What this decided: docs/design-notes.md, \"Free-space ceiling and the bounded fill\" and",
             "\"Wall-contact evidence for the unseen fill (issue 14 item 4)\", \"The unseen fill carried down the",
             "seen slope in the shadows\", \"The wall strip\" and \"`wall-strip` made the default\".", "",
             "## Ve (eq. 8, %) over the phases: mean | sd | max", ""]
    head = "| pile | P_traj | noise | " + " | ".join(f"`{p}` mean | sd | max" for p in policies) + " |"
    lines += [head, "|" + "---|" * (3 + 3 * len(policies))]
    for (pile, p, noise), rs in _rows_by_case(rows):
        cells = [pile, f"{p:g} %", noise] + [_stats([r[f"ve_{pol}_pct"] for r in rs]) for pol in policies]
        lines.append("| " + " | ".join(cells) + " |")
    lines += ["", "## What each fill put into the unseen cells", "",
              "Fill error in the unseen cells alone, sum of (fill - true height) x cell area, in % of the true volume",
              "(mean of |error| over the phases, then the mean signed error): the part of Ve the fill decides, apart",
              "from the fitted surface's own error.", ""]
    head = ("| pile | P_traj | noise | unseen % | crossed % | held % | contacts | pinned % | pin / nearest m | "
            + f"cell error m ({' / '.join(CELL_ERROR_FILLS)}) | "
            + " | ".join(f"`{p}` abs | signed" for p in policies) + " | inside |")
    lines += [head, "|" + "---|" * (11 + 2 * len(policies))]
    for (pile, p, noise), rs in _rows_by_case(rows):
        inside = sum(r["v_lo_m3"] <= r["true_m3"] <= r["v_hi_m3"] for r in rs)
        cells = [pile, f"{p:g} %", noise, f"{np.mean([r['unseen_pct'] for r in rs]):.1f}",
                 f"{np.mean([r['beam_crossed_pct'] for r in rs]):.0f}", f"{np.mean([r['held_pct'] for r in rs]):.1f}"]
        cells += [f"{np.mean(np.abs([r[f'u_{pol}_pct'] for r in rs])):.2f} | "
                  f"{np.mean([r[f'u_{pol}_pct'] for r in rs]):+.2f}" for pol in policies]
        cells.append(f"{inside}/{len(rs)}")
        pin_err = [r["pin_err_m"] for r in rs if math.isfinite(r["pin_err_m"])]
        pin_near = [r["pin_nearest_err_m"] for r in rs if math.isfinite(r["pin_nearest_err_m"])]
        cells[6:6] = [f"{np.mean([r['n_contacts'] for r in rs]):.0f}", f"{np.mean([r['pinned_pct'] for r in rs]):.1f}",
                      f"{np.mean(pin_err):.2f} / {np.mean(pin_near):.2f}" if pin_err else "-",
                      " / ".join(f"{np.mean([r[f'mae_{pol}_m'] for r in rs]):.2f}" for pol in CELL_ERROR_FILLS)]
        lines.append("| " + " | ".join(cells) + " |")
    secs = [r["ceiling_s"] for r in rows]
    lines += ["", "`unseen %`: floor cells without a fitted surface (outside the points' hull, or emptied",
              "where the fit left the building); `crossed %`: of those, the share any beam passed over (the",
              "others' ceiling is the roof); `held %`: the share the bounded thin plate holds at its ceiling;",
              "`contacts`: wall contacts a survey found (mean; most are the bare floor meeting a wall); `pinned %`:",
              "the share of the unseen cells holding one; `pin / nearest m`: in those cells, the mean |height - true",
              "height| of the contacts' estimate and of `nearest`'s copy (the evidence where it exists); `cell",
              "error m`: the mean |fill - true height| over all the unseen cells (a fill can be right per cell and",
              "still lose in the sum, where its errors no longer cancel).",
              "`inside`: phases whose true volume lies between the volume with every unseen cell at the floor",
              "and with every unseen cell at its ceiling (the fitted cells as fitted, so the fit's own error",
              "can put it outside).", "",
              f"Free-space ceiling over the unseen cells: median {np.median(secs) * 1e3:.0f} ms a survey (max "
              f"{max(secs) * 1e3:.0f} ms; {int(np.median([r['n_beams'] for r in rows])):,} beams median; the "
              "campaign shares two cores with other work).", ""]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--piles", nargs="+", default=list(PILES))
    ap.add_argument("--p-traj", nargs="+", type=float, default=list(P_TRAJ_PCT))
    ap.add_argument("--noise", nargs="+", default=list(NOISES), choices=NOISES,
                    help="sensor noise of the simulated surveys (none, or the paper's Appendix A)")
    ap.add_argument("--positions", type=int, default=N_POSITIONS, help="servo phases (1-20)")
    ap.add_argument("--cache", type=Path, default=Path("runs/sweep-cache"))
    ap.add_argument("--out", type=Path, default=Path("docs/unseen.md"))
    args = ap.parse_args(argv)
    for name in args.piles:
        if name not in PILES:
            print(f"unseen_campaign: unknown pile {name!r} (use {', '.join(PILES)})", file=sys.stderr)
            return 2
    if not 1 <= args.positions <= N_POSITIONS:
        print(f"unseen_campaign: --positions must be 1-{N_POSITIONS}", file=sys.stderr)
        return 2
    rows: list[dict] = []
    for noise in args.noise:
        for pile in args.piles:
            for p in args.p_traj:
                rs = run_case(pile, p, servo_positions(args.positions), args.cache, noise_name=noise)
                rows += rs
                print(f"{pile} P_traj {p:g} % noise {noise}: " + ", ".join(
                    f"{pol} {np.mean([r[f've_{pol}_pct'] for r in rs]):.2f}" for pol in FILLS), flush=True)
    command = "python -m tools.unseen_campaign" + (" " + " ".join(argv) if argv else "")
    write_markdown(rows, args.out, FILLS, command)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
