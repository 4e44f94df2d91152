"""An evaluation set of surveys for calibrating the volume's uncertainty (issue 14): many pile shapes,
buildings, altitudes, P_traj, servo phases and sensor-noise models, with a fixed calibration / held-out split.

Each *instance* is a pile (`sitl.world.shapes`: family + seed) in one building flown at one altitude. Each
(instance, P_traj) is one sweep case: one JSBSim flight of that mission (cached by content, shared across
piles and runs), sampled by the batch path (`sample_flight`) at 3 servo phases (of the 20, drawn from the
case) x 3 noise models. Every run's samples (`samples.npy`), log header and truth are stored under
`ROOT/runs/<run id>/` so the ground station can be re-run on all of them without re-sampling
(`iter_runs`, `load_run`, `survey_of`); the rows of today's ground station go to `ROOT/rows.csv`, a
summary to `docs/evaluation_set.md`.

    python -m tools.evalset --jobs 1 --write docs/evaluation_set.md     # the full set (~1,500 runs)
    python -m tools.evalset --quick --root /tmp/evalset                  # a few runs (tests)
"""

from __future__ import annotations

import csv
import functools
import json
import math
import os
import statistics
import sys
import time
from collections import Counter, defaultdict
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from pathlib import Path

import numpy as np

from firmware_py.core.cli import ArgumentParser
from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission
from sitl.runners.flight import PAYLOAD_1D_KG, FlownMission, fly_mission
from sitl.runners.fly import FlyConfig, check_clearance, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.world.raycast import World
from sitl.world.shapes import Family, Shape, make_shape
from tools.sweep import Case, cached, content_key, missing_cases, read_rows_csv, run_sweep, write_rows_csv
from tools.workers import worker_pool

EVALSET_VERSION = "3"
"""Part of every case (and so of its cache key): bump it when what a case computes changes. 2: Appendix A's
pose errors interpolated between messages, as the payload now tags samples. 3: the ground station's default
surface fit became `local-linear` (its rows were computed with the limited cubic until regenerated)."""
FLIGHT_VERSION = "1"
"""Part of every flight key (tools.experiments' flights key on P_traj only: they are all the paper's building)."""
P_TRAJ_PCT = (5, 10, 15, 20, 25, 30, 35)
NOISES = tuple(SensorNoiseModel)
N_SERVO_POSITIONS = 20
PHASES_PER_CASE = 3
PILE_CLEARANCE_M = 2.0
"""Least height between the pile's top and the flight altitude: 4x the mission's 0.5 m clearance to walls and
roof (sitl.missions.rectangle), for the vehicle's altitude-hold error and its size; piles are made to fit it."""
ROOF_CLEARANCE_M = 3.0
"""The higher altitude flown is the roof less this (the paper: 12 m under a 15 m roof)."""
DEFAULT_ROOT = Path("runs/evalset")
DEFAULT_FLIGHT_CACHE = Path("runs/sweep-cache")


class Split(StrEnum):
    CALIBRATION = "calibration"
    HELDOUT = "heldout"


@dataclass(frozen=True)
class Building:
    """A building and the altitudes flown in it (the higher one ROOF_CLEARANCE_M under the roof)."""

    name: str
    storage: Storage
    altitudes_m: tuple[float, ...]

    def __post_init__(self) -> None:
        for a in self.altitudes_m:
            Mission(storage=self.storage, altitude_m=a)  # fits under the roof with the vehicle's clearance
            if a - PILE_CLEARANCE_M <= 0:
                raise ValueError(f"{self.name}: altitude {a} m leaves no room for a pile")


def _building(name: str, storage: Storage, low_frac: float) -> Building:
    high = storage.height_m - ROOF_CLEARANCE_M
    return Building(name, storage, (high, float(round(low_frac * storage.height_m))))


BUILDINGS: tuple[Building, ...] = (
    _building("paper", Storage(60.0, 40.0, 15.0), 0.6),   # 12 m (the paper's) and 9 m
    _building("small", Storage(40.0, 25.0, 12.0), 0.6),   # 9 m and 7 m
    _building("long", Storage(80.0, 30.0, 15.0), 0.67),   # 12 m and 10 m
)
BUILDING_BY_NAME = {b.name: b for b in BUILDINGS}

PLAN: dict[str, tuple[Family, ...]] = {
    "paper": (*Family, Family.IRREGULAR, Family.CORNER),
    "small": (Family.CONE, Family.CORNER, Family.WALL, Family.BAY, Family.IRREGULAR),
    "long": (Family.RIDGE, Family.CORNER, Family.WALL, Family.STEEP, Family.IRREGULAR),
}
"""The piles of each building: every family in the paper's building (two each of the paper's generator, the
most varied, and of the corner pile, the hardest), the common and hard ones in the others. 24 piles x 7 P_traj x
3 phases x 3 noise models = 1,512 runs: what this machine computes in about an hour."""

HELDOUT_BUILDINGS = frozenset({"long"})
HELDOUT_FAMILIES = frozenset({Family.SEPARATE})
HELDOUT_SEED_MODULUS = 4
"""An instance of the other buildings and families is held out when seed % 4 == 1: whole piles, never a phase or
a noise draw of a flight whose twin is in the calibration part."""


@dataclass(frozen=True)
class Instance:
    """A pile in a building, flown at one altitude."""

    building: str
    family: Family
    seed: int
    altitude_m: float

    @property
    def max_top_m(self) -> float:
        return self.altitude_m - PILE_CLEARANCE_M

    @property
    def split(self) -> Split:
        return split_of(self.building, self.family, self.seed)

    def shape(self) -> Shape:
        return make_shape(self.family, BUILDING_BY_NAME[self.building].storage, self.max_top_m, self.seed)


def split_of(building: str, family: Family | str, seed: int) -> Split:
    """The fixed split: held-out buildings and families whole, and one pile in four of the rest."""
    if building in HELDOUT_BUILDINGS or Family(family) in HELDOUT_FAMILIES or seed % HELDOUT_SEED_MODULUS == 1:
        return Split.HELDOUT
    return Split.CALIBRATION


def instances() -> list[Instance]:
    """Every pile of the set (PLAN). Seeds run on across buildings, so no two piles share (family, seed); the
    piles of a building alternate between its altitudes in PLAN's order, except steep piles, which go as high as
    the higher altitude allows."""
    out: list[tuple[int, int, Instance]] = []
    next_seed: Counter[Family] = Counter()
    for j, b in enumerate(BUILDINGS):
        for i, fam in enumerate(PLAN[b.name]):
            seed = next_seed[fam]
            next_seed[fam] += 1
            alt = max(b.altitudes_m) if fam is Family.STEEP else b.altitudes_m[i % len(b.altitudes_m)]
            out.append((i, j, Instance(b.name, fam, seed, alt)))
    # buildings interleaved (the first pile of each, then the second ...): a set stopped part way is still varied
    return [inst for _, _, inst in sorted(out, key=lambda t: (t[0], t[1]))]


def quick_instances() -> list[Instance]:
    """A small subset for tests and a smoke run: the first corner pile of the small building and the empty one."""
    small_corner = next(i for i in instances() if i.building == "small" and i.family is Family.CORNER)
    empty = next(i for i in instances() if i.family is Family.EMPTY)
    return [small_corner, empty]


def cases_for(insts: list[Instance], p_traj_pct=P_TRAJ_PCT, phases: int = PHASES_PER_CASE,
              noises=NOISES) -> list[Case]:
    return [Case.make("evalset", building=i.building, family=i.family.value, seed=i.seed, altitude_m=i.altitude_m,
                      p_traj_pct=int(p), phases=phases, noises=",".join(n.value for n in noises),
                      version=EVALSET_VERSION)
            for i in insts for p in p_traj_pct]


def phases_of(case: Case) -> list[int]:
    """The case's servo initial positions: `phases` of the 20, drawn from the case (not the same ones everywhere)."""
    rng = np.random.default_rng(int(content_key(case.as_dict()), 16))
    return sorted(int(k) for k in rng.choice(N_SERVO_POSITIONS, size=case.get("phases"), replace=False))


def instance_of(case: Case) -> Instance:
    return Instance(case.get("building"), Family(case.get("family")), case.get("seed"), case.get("altitude_m"))


# ----- flights and runs ------------------------------------------------------------------------------------------


def mission_for(building: str, altitude_m: float, p_traj_pct: float) -> Mission:
    return Mission(storage=BUILDING_BY_NAME[building].storage, p_traj=p_traj_pct / 100.0, altitude_m=altitude_m)


def flight(mission: Mission, frame: StorageFrame, cache_dir: Path) -> FlownMission:
    """The JSBSim flight of this mission (the pile does not change it), cached by the mission's content."""
    key = "evalset-flight-" + content_key({"v": FLIGHT_VERSION, "mission": mission.to_dict(),
                                             "payload_kg": PAYLOAD_1D_KG})
    return cached(cache_dir, key, lambda: fly_mission(mission, frame, payload_kg=PAYLOAD_1D_KG))


def run_id(inst: Instance, p_traj_pct: int, phase: int, noise: SensorNoiseModel) -> str:
    return (f"{inst.building}-{inst.family.value}-{inst.seed}-a{inst.altitude_m:g}-p{p_traj_pct}-ph{phase}-"
            f"{noise.value}")


def _save_run(path: Path, samples: np.ndarray, header: dict, truth: dict) -> None:
    """samples.npy, header.json, then truth.json last (its presence marks a complete run), each via os.replace."""
    path.mkdir(parents=True, exist_ok=True)
    for name, write in (("samples.npy", lambda f: np.save(f, samples)),
                        ("header.json", lambda f: f.write(json.dumps(header).encode())),
                        ("truth.json", lambda f: f.write(json.dumps(truth, indent=1).encode()))):
        tmp = path / f".{name}.tmp"
        with open(tmp, "wb") as f:
            write(f)
        os.replace(tmp, path / name)


def survey_metrics(sv, true_m3: float) -> dict:
    """What today's ground station made of one run: volume, errors, coverage and what the fill invented."""
    from ground.surface import grid_volume, reconstructed_ratio_pct

    volume = grid_volume(sv.heights, sv.grid)
    filled = ~np.isfinite(sv.heights_fit) & np.isfinite(sv.heights)
    err = volume - true_m3
    ve = 100.0 * err / true_m3 if true_m3 > 0 else None
    return {"volume_m3": volume, "error_m3": err, "ve_pct": ve, "ve_abs_pct": None if ve is None else abs(ve),
            "ra_pct": reconstructed_ratio_pct(sv.heights_fit), "filled_cell_frac": float(filled.mean()),
            "filled_volume_m3": float(np.sum(sv.heights[filled]) * sv.grid.cell_area_m2),
            "n_points": len(sv.pile_points_w)}


def run_case(case: Case, root: Path = DEFAULT_ROOT, flight_cache: Path = DEFAULT_FLIGHT_CACHE) -> list[dict]:
    """The runs of one (instance, P_traj): sample, store, survey with today's ground station."""
    from ground.report import ReportOptions, survey_from_samples

    inst, p = instance_of(case), case.get("p_traj_pct")
    noises = [SensorNoiseModel(n) for n in case.get("noises").split(",")]
    shape = inst.shape()
    mission = mission_for(inst.building, inst.altitude_m, p)
    if mission.altitude_m - shape.pile.max_height_m < PILE_CLEARANCE_M - 1e-9:
        raise ValueError(f"{shape.name}: its top {shape.pile.max_height_m:.2f} m is less than {PILE_CLEARANCE_M:g} m "
                         f"under the {mission.altitude_m:g} m flight")
    check_clearance(mission, shape.pile)
    base = FlyConfig(mission=mission, stockpile=shape.name)
    flown = flight(mission, base.frame, Path(flight_cache))
    if not flown.completed:
        raise RuntimeError(f"{inst}, P_traj {p} %: the vehicle did not complete the mission")
    storage = mission.storage
    world = World(storage, shape.pile, base.lidar.max_range_m)
    t = np.arange(int(flown.duration_s * base.lidar.rate_hz) + 1) / base.lidar.rate_hz
    traj = flown.trajectory_at(t)
    fam_i = list(Family).index(inst.family)
    b_i = [b.name for b in BUILDINGS].index(inst.building)
    rows = []
    for k in phases_of(case):
        for noise_model in noises:
            cfg = replace(base, initial_position=k, sensor_noise=noise_model)
            wf = cfg.servo_waveform()
            noise = SensorNoise.of(noise_model, cfg.lidar)
            t0 = time.perf_counter()
            samples = sample_flight(traj, wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame, noise=noise,
                                    seed=[b_i, fam_i, inst.seed, round(inst.altitude_m * 10), p, k,
                                          NOISES.index(noise_model)])
            t_sample = time.perf_counter() - t0
            header = log_header(cfg, wf)
            rid = run_id(inst, p, k, noise_model)
            truth = {"run_id": rid, "true_volume_m3": shape.volume_m3, "shape": shape.name,
                     "family": inst.family.value, "seed": inst.seed, "shape_source": shape.pile.source,
                     "shape_params": shape.params, "analytic_volume_m3": shape.analytic_volume_m3,
                     "height_field": shape.height_field, "building": inst.building, "storage": storage.to_dict(),
                     "altitude_m": inst.altitude_m, "p_traj_pct": p, "phase": k, "noise": noise_model.value,
                     "split": inst.split.value, "evalset_version": EVALSET_VERSION}
            _save_run(Path(root) / "runs" / rid, samples, header, truth)
            t0 = time.perf_counter()
            sv = survey_from_samples(samples, header, storage, cfg.frame, np.array(cfg.lever_arm_body_m),
                                     ReportOptions(plots=False))
            t_survey = time.perf_counter() - t0
            rows.append({"run_id": rid, "split": inst.split.value, "phase": k, "noise": noise_model.value,
                         "true_volume_m3": shape.volume_m3, **survey_metrics(sv, shape.volume_m3),
                         "height_field": shape.height_field, "n_samples": len(samples),
                         "sample_s": t_sample, "survey_s": t_survey})
    return rows


# ----- reading the set back ----------------------------------------------------------------------------------------


@dataclass(frozen=True)
class EvalRun:
    """One stored run: what `survey_from_samples` needs, and the truth to score it against."""

    path: Path
    samples: np.ndarray
    header: dict
    truth: dict
    storage: Storage
    frame: StorageFrame
    lever_arm_body_m: np.ndarray

    @property
    def run_id(self) -> str:
        return self.truth["run_id"]

    @property
    def true_volume_m3(self) -> float:
        return float(self.truth["true_volume_m3"])

    @property
    def split(self) -> Split:
        return Split(self.truth["split"])


def load_run(path: str | Path) -> EvalRun:
    """A stored run (ValueError naming the file when it is incomplete or unreadable)."""
    path = Path(path)
    try:
        truth = json.loads((path / "truth.json").read_text())
        header = json.loads((path / "header.json").read_text())
        samples = np.load(path / "samples.npy", allow_pickle=False)
        storage = Storage.from_dict(header["storage"])
        frame = StorageFrame.from_dict(header["storage_frame"])
        lever = np.asarray(header.get("lever_arm_body_m", [0.0, 0.0, 0.0]), dtype=float)
    except (OSError, ValueError, KeyError, TypeError) as exc:
        raise ValueError(f"evaluation run {path} is incomplete or unreadable: {type(exc).__name__}: {exc}") from None
    return EvalRun(path, samples, header, truth, storage, frame, lever)


def run_dirs(root: str | Path = DEFAULT_ROOT, split: Split | str | None = None) -> list[Path]:
    """The complete runs (truth.json written) under root, sorted by id; only one split's when given."""
    want = None if split in (None, "all") else Split(split)
    out = []
    for d in sorted((Path(root) / "runs").glob("*/truth.json")):
        if want is None or json.loads(d.read_text()).get("split") == want.value:
            out.append(d.parent)
    return out


def stored_runs_or_say(root: str | Path, stride: int, prog: str) -> list[str]:
    """Every stride-th complete run under root, as paths; none (and one line on stderr naming prog and how to make
    them) when there are none: the checks that read the stored set exit 2 then."""
    dirs = [str(d) for d in run_dirs(root)[::stride]]
    if not dirs:
        print(f"{prog}: no stored runs under {root} (python -m tools.evalset makes them)", file=sys.stderr)
    return dirs


def runs_where(root: str | Path, noises: Sequence[str], p_traj: Sequence[int] | None = None) -> list[str]:
    """The complete runs under root of these noise models (and P_traj, None: all), as paths: chosen by what each run's
    truth.json says it is."""
    out = []
    for d in run_dirs(root):
        t = json.loads((d / "truth.json").read_text())
        if t.get("noise") in noises and (p_traj is None or t.get("p_traj_pct") in p_traj):
            out.append(str(d))
    return out


def rows_of_runs(root: Path, run_row: Callable[[str], dict | None], noises: Sequence[str],
                 p_traj: Sequence[int] | None, jobs: int, chunksize: int = 4) -> list[dict] | None:
    """run_row over the chosen stored runs in `jobs` processes, with a line of progress every 50 runs; its None rows
    (runs with nothing to compare) left out. None, with one line on stderr, when root holds no evaluation set or none
    of its runs is chosen: the tools that tabulate such rows exit 2 then."""
    if not (Path(root) / "runs").is_dir():
        print(f"no evaluation set at {root} (python -m tools.evalset makes one)", file=sys.stderr)
        return None
    chosen = runs_where(root, noises, p_traj)
    if not chosen:
        print(f"no stored runs match under {root}", file=sys.stderr)
        return None
    t0 = time.perf_counter()
    rows = []
    with worker_pool(jobs) as pool:
        for i, row in enumerate(pool.map(run_row, chosen, chunksize=chunksize), 1):
            if row is not None:
                rows.append(row)
            if i % 50 == 0 or i == len(chosen):
                print(f"  {i}/{len(chosen)} runs ({time.perf_counter() - t0:.0f} s)", file=sys.stderr)
    return rows


def rows_of_file(path: Path) -> list[dict] | None:
    """Rows a tool wrote with --rows (`tools.sweep.read_rows_csv`); None, with one line on stderr naming the file,
    when it is missing, unreadable or not text."""
    if not path.is_file():
        print(f"no rows file at {path}", file=sys.stderr)
        return None
    try:
        return read_rows_csv(path)
    except (OSError, ValueError, csv.Error) as exc:  # unreadable, or not text
        print(f"{path}: cannot be read as rows ({type(exc).__name__}: {exc})"[:300], file=sys.stderr)
        return None


def add_rows_options(ap: ArgumentParser) -> None:
    """The options of a tool that tabulates a row function over the stored runs (`rows_of_options` reads them)."""
    ap.add_argument("--root", type=Path, default=Path("runs/evalset"), help="the evaluation set (tools/evalset.py)")
    ap.add_argument("--p-traj", type=int, nargs="+", default=None, help="only these P_traj (percent)")
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument("--rows", type=Path, default=None, help="also write the per-run rows (CSV)")
    ap.add_argument("--from-rows", type=Path, default=None, help="tabulate these rows instead of running")
    ap.add_argument("--write", type=Path, default=None, help="the Markdown page to (re)write the tables in")


def rows_of_options(ap: ArgumentParser, args, run_row: Callable[[str], dict | None], noises: Sequence[str],
                    chunksize: int = 4) -> list[dict] | None:
    """The rows `add_rows_options` asks for: read back from --from-rows (`rows_of_file`), or run_row over the chosen
    runs (`rows_of_runs`) and written to --rows; None when there are none to tabulate (one line on stderr)."""
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    if args.from_rows is not None:
        return rows_of_file(args.from_rows)
    rows = rows_of_runs(args.root, run_row, noises, args.p_traj, args.jobs, chunksize)
    if rows is not None and args.rows is not None:
        write_rows_csv(rows, args.rows)
    return rows


def iter_runs(split: Split | str | None = None, root: str | Path = DEFAULT_ROOT) -> Iterator[EvalRun]:
    """Every stored run of the split ("calibration", "heldout", or None / "all"), in a fixed order."""
    for d in run_dirs(root, split):
        yield load_run(d)


def survey_of(run: EvalRun, opts=None):
    """Today's (or any) ground station on a stored run: `survey_from_samples` with the run's own geometry."""
    from ground.report import ReportOptions, survey_from_samples

    return survey_from_samples(run.samples, run.header, run.storage, run.frame, run.lever_arm_body_m,
                               opts if opts is not None else ReportOptions(plots=False))


# ----- summary ---------------------------------------------------------------------------------------------------


def _fmt(v: float | None, digits: int = 2) -> str:
    return "-" if v is None or not math.isfinite(v) else f"{v:.{digits}f}"


def summary_table(rows: list[dict]) -> str:
    """Median and max |Ve| by shape family x P_traj, one column pair per noise model (empty building: |error| m^3)."""
    groups: dict[tuple[str, int, str], list[dict]] = defaultdict(list)
    for r in rows:
        groups[(r["family"], r["p_traj_pct"], r["noise"])].append(r)
    noises = [n.value for n in NOISES if any(k[2] == n.value for k in groups)]
    head = "| family | P_traj | runs | " + " | ".join(f"{n}: median / max \\|Ve\\| [%]" for n in noises) + " |"
    out = [head, "|---|---|---|" + "---|" * len(noises)]
    for fam in [f.value for f in Family]:
        for p in P_TRAJ_PCT:
            cells, n = [], 0
            for noise in noises:
                g = groups.get((fam, p, noise), [])
                n += len(g)
                if not g:
                    cells.append("-")
                elif fam == Family.EMPTY.value:
                    e = [abs(r["error_m3"]) for r in g]
                    cells.append(f"\\|error\\| {statistics.median(e):.1f} / {max(e):.1f} m³")
                else:
                    v = [r["ve_abs_pct"] for r in g if r["ve_abs_pct"] is not None]
                    cells.append(f"{_fmt(statistics.median(v))} / {_fmt(max(v))}" if v else "-")
            if n:
                out.append(f"| {fam} | {p} % | {n} | " + " | ".join(cells) + " |")
    return "\n".join(out)


def fill_table(rows: list[dict]) -> str:
    """Per family: coverage (R_a), what the empty-cell fill invented, and how often that bounds the error."""
    out = ["| family | runs | median R_a [%] | median filled cells [%] | median volume in filled cells [m³] | "
           "median \\|error\\| [m³] | runs with \\|error\\| <= \\|volume in filled cells\\| |",
           "|---|---|---|---|---|---|---|"]
    for fam in [f.value for f in Family]:
        g = [r for r in rows if r["family"] == fam]
        if not g:
            continue
        bound = sum(abs(r["error_m3"]) <= abs(r["filled_volume_m3"]) for r in g)
        out.append(f"| {fam} | {len(g)} | {statistics.median(r['ra_pct'] for r in g):.1f} | "
                   f"{100 * statistics.median(r['filled_cell_frac'] for r in g):.1f} | "
                   f"{statistics.median(r['filled_volume_m3'] for r in g):.1f} | "
                   f"{statistics.median(abs(r['error_m3']) for r in g):.1f} | {bound} of {len(g)} |")
    return "\n".join(out)


def split_table(rows: list[dict]) -> str:
    out = ["| split | piles (instances) | runs | families | buildings |", "|---|---|---|---|---|"]
    for s in Split:
        g = [r for r in rows if r["split"] == s.value]
        piles = {(r["building"], r["family"], r["seed"]) for r in g}
        fams = Counter(r["family"] for r in g)
        out.append(f"| {s.value} | {len(piles)} | {len(g)} | "
                   + ", ".join(f"{f} {fams[f]}" for f in [x.value for x in Family] if fams[f]) + " | "
                   + ", ".join(sorted({r["building"] for r in g})) + " |")
    return "\n".join(out)


def document(rows: list[dict], wall_s: float, n_computed: int, jobs: int, command: str) -> str:
    from ground.surface import DEFAULT_EMPTY_CELLS
    cost = [r["sample_s"] + r["survey_s"] for r in rows]
    med = statistics.median(cost) if cost else float("nan")
    total_h = sum(cost) / 3600
    bl = "\n".join(f"| {b.name} | {b.storage} | {', '.join(f'{a:g} m' for a in b.altitudes_m)} |" for b in BUILDINGS)
    return "\n".join([
        "# Evaluation set for the volume's uncertainty",
        "",
        f"Generated by `{command}` (this run: {wall_s / 60:.1f} min wall, {n_computed} of the cases computed, "
        f"{jobs} worker(s); the rest read from the cache). Everything below is measured on the stored runs.",
        "",
        "## What is in it",
        "",
        "Piles from `sitl/world/shapes.py` (cone, ridge, corner, wall, bay, flat, steep, separate, irregular = the "
        "paper's generator with other seeds and height ranges, box with vertical faces, sphere resting on the floor, "
        "empty building), each made to fit its building with its top at least "
        f"{PILE_CLEARANCE_M:g} m under the flight altitude. Buildings and the altitudes flown (the higher one "
        f"{ROOF_CLEARANCE_M:g} m under the roof; each pile is flown at one of them, alternating with its seed; steep "
        "piles at the higher):",
        "",
        "| building | inside (L x W x H) | altitudes |",
        "|---|---|---|",
        bl,
        "",
        f"Each pile is flown at P_traj {', '.join(map(str, P_TRAJ_PCT))} % (the JSBSim vehicle, the baseline mission: "
        f"1 m/s, 30 deg/s yaw, one-step corners; one flight per building x altitude x P_traj, cached), and each "
        f"flight is sampled by the batch path at {PHASES_PER_CASE} servo initial positions (of the 20, drawn per "
        f"case from its key) x the noise models {', '.join(n.value for n in NOISES)} (seeded per run). Every run "
        "keeps its samples (`samples.npy`), log header and truth under `runs/evalset/runs/<run id>/`: "
        "`tools.evalset.iter_runs(split)` / `load_run(path)` / `survey_of(run, opts)` re-run any ground station on "
        "them without re-sampling. `runs/evalset/rows.csv` has one row per run (today's ground station: volume, "
        "truth, signed and absolute Ve, R_a, the fraction of cells the empty-cell fill invented and the volume "
        "it put there, points).",
        "",
        "## Split",
        "",
        f"Whole piles, never a phase or a noise draw of a flight whose twin is on the other side: held out are the "
        f"building(s) {', '.join(sorted(HELDOUT_BUILDINGS))} (never seen in calibration), the famil(ies) "
        f"{', '.join(sorted(f.value for f in HELDOUT_FAMILIES))}, and every other pile whose seed % "
        f"{HELDOUT_SEED_MODULUS} == 1 (`tools.evalset.split_of`).",
        "",
        split_table(rows),
        "",
        "## Cost",
        "",
        f"{len(rows)} runs; per run (sampling + today's ground station, wall time in a worker niced on a 2-core "
        f"machine shared with other jobs) median {med:.2f} s, {total_h:.2f} worker-hours in all (the runs' "
        "`sample_s` + `survey_s`; flights excluded: a JSBSim flight takes about a second, one per building x "
        "altitude x P_traj). The stored runs take ~3.5 MB each (`samples.npy`).",
        "",
        "## Today's ground station on the set",
        "",
        "|Ve| = |V - V_true| / V_true (eq. 8); median / max over the runs of each row (piles, phases).",
        "",
        summary_table(rows),
        "",
        f"What the empty-cell fill (`{DEFAULT_EMPTY_CELLS}`, the default) did, per family, over all noise models and "
        "P_traj: filled cells are those without a fitted surface (NaN in `heights_fit`) that the fill gave a height.",
        "",
        fill_table(rows),
        "",
    ])


def main(argv: list[str] | None = None) -> int:
    ap = ArgumentParser(prog="python -m tools.evalset", description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="a small subset (2 piles, P_traj 35 %%, 1 phase)")
    ap.add_argument("--jobs", type=int, default=1, help="worker processes (default 1)")
    ap.add_argument("--root", type=Path, default=DEFAULT_ROOT, help="where the runs, the case cache and rows.csv go")
    ap.add_argument("--flight-cache", type=Path, default=DEFAULT_FLIGHT_CACHE, help="JSBSim flight cache")
    ap.add_argument("--write", type=Path, default=None, help="write the summary page here (docs/evaluation_set.md)")
    ap.add_argument("--noises", default=None, help="comma-separated subset of the noise models (default: all)")
    ap.add_argument("--no-progress", action="store_true", help="no progress bar")
    ap.add_argument("--cached-only", action="store_true",
                    help="compute nothing: rows, CSV and page from the cases already cached")
    args = ap.parse_args(argv)
    if args.jobs < 1:
        ap.error("--jobs must be >= 1")
    try:
        noises = NOISES if args.noises is None else tuple(SensorNoiseModel(n.strip()) for n in args.noises.split(","))
    except ValueError:
        ap.error(f"--noises must be a comma-separated subset of {', '.join(n.value for n in NOISES)}, "
                 f"got {args.noises!r}")
    if args.quick:
        cases = cases_for(quick_instances(), p_traj_pct=(35,), phases=1, noises=noises)
    else:
        cases = cases_for(instances(), noises=noises)
    cache = args.root / "cases"
    missing = missing_cases(cases, cache)
    n_todo = len(missing)
    t0 = time.perf_counter()
    if args.cached_only:  # the cases already computed (a set still running, or stopped part way)
        gone = {c.key for c in missing}
        cases = [c for c in cases if c.key not in gone]
        print(f"--cached-only: {len(cases)} cases cached, {n_todo} not yet computed (left out)")
        n_todo = 0
    fn = functools.partial(run_case, root=args.root, flight_cache=args.flight_cache)
    rows = run_sweep(cases, fn, cache, jobs=args.jobs, progress=not args.no_progress, desc="evalset")
    wall = time.perf_counter() - t0
    write_rows_csv(rows, args.root / "rows.csv")
    print(summary_table(rows))
    print(f"{len(rows)} runs ({n_todo} of {len(cases)} cases computed) in {wall / 60:.1f} min; "
          f"rows in {args.root / 'rows.csv'}")
    if args.write is not None:
        cmd = ("python -m tools.evalset" + (" --quick" if args.quick else "")
               + (f" --noises {args.noises}" if args.noises else "") + (" --cached-only" if args.cached_only else "")
               + f" --jobs {args.jobs} --write {args.write}")
        args.write.parent.mkdir(parents=True, exist_ok=True)
        args.write.write_text(document(rows, wall, n_todo, args.jobs, cmd))
    return 0


if __name__ == "__main__":
    sys.exit(main())
