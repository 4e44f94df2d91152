"""The paper's experiments as data, and the function that runs one case of them.

An `Experiment` is one configuration of Sec. 4 (waveform, speed, yaw-rate limit, corner turns,
sensor, noise); a case is (experiment, stockpile, P_traj). A case flies once (the JSBSim vehicle;
the flight depends on the mission and the payload mass, not on the pile, so flights are cached
and shared across piles), then samples that flight for each of the 20 servo initial positions of
Fig. 9 (and each noise draw) through the same vectorised math the run-directory path uses, and
computes Ve (eq. 8, both empty-cell policies), R_a (eq. 9) and the flight's energy. The 2D and 3D
LiDARs scan the same kind of flight (with their own payload mass) and go through the ground
station's binned path. Experiments can also be read from a TOML file:

    [[experiment]]
    name = "yaw-6"
    figure = "Fig. 17"
    yaw_rate_max_dps = 6
"""

from __future__ import annotations

import math
import time
import tomllib
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path

import numpy as np

from firmware_py.core.frames import StorageFrame
from firmware_py.core.sensor_noise import SensorNoise, SensorNoiseModel
from ground.report import ReportOptions, survey_from_samples
from ground.surface import (
    CONTACT_POLICIES,
    DEFAULT_EMPTY_CELLS,
    EMPTY_CELL_POLICIES,
    fill_empty,
    grid_volume,
    reconstructed_ratio_pct,
    volume_error_pct,
)
from sitl.missions.rectangle import TURN_MODES, Mission
from sitl.runners.flight import PAYLOAD_1D_KG, FlownMission, fly_mission
from sitl.runners.fly import PLANTS, FlyConfig, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.vehicle.ideal_plant import IdealPlant
from sitl.world.raycast import World
from sitl.world.stockpile import paper_pile
from tools.sweep import Case, cached

SWEEP_VERSION = "16"
"""Part of every case key: bump it when the simulation or the ground station changes what a case
computes (the cache cannot see code). 3: runaway surface cells are emptied, not clamped to the floor;
4: the cubic surface is limited to its triangles' data by default, despiking, servo re-timing;
5: Appendix A's noise through sitl.sensing.noise (servo error on the true beam, pose error per
pose message, the header's sensor_noise record); 6: the pose errors interpolated between the messages on
either side of a sample, as the payload now tags (it waits for the pose after the sample); 7: the wall-contact
fill is the default empty-cell policy; 8: its Ve column is the survey's own fill (it had been `nearest`'s);
9: the despiking allows the header's per-sample pointing error (Appendix A); 10: the default surface fit is
`local-linear`; 11: its windows' standard errors scaled to the data's own scatter; 12: the ground station of
2026-11-30 (the pose correction runs by default; a straight stretch of sweep up a wall is the wall's); 13: the unseen
fill held under the free-space ceiling carried at the steepest slope (2026-12-02); 14: the `carry-down` fill is the
default (2026-12-03); 15: the `wall-strip` fill is the default (2026-12-03); 16: `--surface-slopes gp-bridges`
is the default (2026-12-05)."""
FLIGHT_VERSION = "2"
"""Part of every flight key. 2: the autopilot flies towards the target through corners."""
P_TRAJ_PCT = (5, 10, 15, 20, 25, 30)
PILES = ("1", "2")
N_POSITIONS = 20
SENSORS = ("1d", "2d", "3d")


@dataclass(frozen=True)
class Experiment:
    """One configuration of the paper's Sec. 4 (defaults: the baseline of Table 1)."""

    name: str
    figure: str = ""
    sensor: str = "1d"
    waveform: str = "semi-triangular"
    speed_m_s: float = 1.0
    yaw_rate_max_dps: float = 30.0
    turn: str = "one-step"
    noise_draws: int = 0
    plant: str = "jsbsim"

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name.replace("-", "").replace("_", "").replace(".", "").isalnum():
            raise ValueError(f"experiment name must be letters, digits, '-', '_' or '.', got {self.name!r}")
        for key in ("figure", "sensor", "waveform", "turn", "plant"):  # a config file can hold any TOML value
            if not isinstance(getattr(self, key), str):
                raise ValueError(f"experiment {self.name}: {key} must be a string, got {getattr(self, key)!r}")
        for key in ("speed_m_s", "yaw_rate_max_dps"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int | float):
                raise ValueError(f"experiment {self.name}: {key} must be a number, got {v!r}")
        if self.sensor not in SENSORS:
            raise ValueError(f"experiment {self.name}: sensor must be one of {', '.join(SENSORS)}, got {self.sensor!r}")
        if self.turn not in TURN_MODES:
            raise ValueError(f"experiment {self.name}: turn must be one of {', '.join(TURN_MODES)}, got {self.turn!r}")
        n = self.noise_draws
        if isinstance(n, bool) or not (isinstance(n, int) and 0 <= n <= 1000):
            raise ValueError(f"experiment {self.name}: noise_draws must be 0-1000, got {self.noise_draws!r}")
        if self.plant not in PLANTS:
            raise ValueError(f"experiment {self.name}: plant must be one of {', '.join(PLANTS)}, got {self.plant!r}")
        if self.noise_draws and self.sensor != "1d":
            raise ValueError(f"experiment {self.name}: noise draws are for the 1D LiDAR (Appendix A)")
        try:
            self.mission(5)  # speed, yaw rate: validated by Mission
            FlyConfig(waveform=self.waveform)  # the waveform name
        except ValueError as exc:
            raise ValueError(f"experiment {self.name}: {exc}") from None

    @property
    def payload_kg(self) -> float:
        """The sensor's mass (Sec. 4.5: 40 g, 370 g, 830 g)."""
        if self.sensor == "1d":
            return PAYLOAD_1D_KG
        from sitl.sensing.scanners import HOKUYO_UTM_30LX, VELODYNE_PUCK_LITE
        return (HOKUYO_UTM_30LX if self.sensor == "2d" else VELODYNE_PUCK_LITE).payload_kg

    def mission(self, p_traj_pct: float) -> Mission:
        return Mission(p_traj=p_traj_pct / 100.0, speed_m_s=self.speed_m_s, turn=self.turn,
                       yaw_rate_max_rad_s=math.radians(self.yaw_rate_max_dps))

    def flight_key(self, p_traj_pct: float) -> str:
        """What the flight depends on (not the pile, the waveform or the noise)."""
        return (f"flight-v{FLIGHT_VERSION}-{self.plant}-p{p_traj_pct:g}-v{self.speed_m_s:g}"
                f"-yaw{self.yaw_rate_max_dps:g}-{self.turn}-m{self.payload_kg:g}")


PAPER_EXPERIMENTS: tuple[Experiment, ...] = (
    Experiment("baseline", "Fig. 11, 19, 20; Table 2"),
    Experiment("sinusoidal", "Fig. 13", waveform="sinusoidal"),
    Experiment("speed-0.5", "Fig. 14", speed_m_s=0.5),
    Experiment("speed-2", "Fig. 14", speed_m_s=2.0),
    Experiment("two-step", "Fig. 16", turn="two-step"),
    Experiment("yaw-17", "Fig. 17, 18", yaw_rate_max_dps=17.0),
    Experiment("yaw-6", "Fig. 17, 18; Table 2", yaw_rate_max_dps=6.0),
    Experiment("yaw-1", "Fig. 17, 18; Table 2", yaw_rate_max_dps=1.0),
    Experiment("2d", "Fig. 22, 23; Table 2", sensor="2d"),
    Experiment("3d", "Fig. 22, 23; Table 2", sensor="3d"),
)
"""What `python -m tools.reproduce` runs by default: every configuration of Table 2 and Sec. 4."""

NOISE_EXPERIMENT = Experiment("noise", "Fig. A1", noise_draws=20)
"""Appendix A: 20 noise draws for each servo position (400 surveys a point): run on request."""

IDEAL_EXPERIMENT = Experiment("baseline-ideal", "Fig. 11 (ideal plant)", plant="ideal")
"""The baseline flown by the kinematic plant (no flight dynamics): what the autopilot costs."""

ALL_EXPERIMENTS = {e.name: e for e in (*PAPER_EXPERIMENTS, NOISE_EXPERIMENT, IDEAL_EXPERIMENT)}


def load_experiments(path: str | Path) -> list[Experiment]:
    """Experiments from a TOML file ([[experiment]] tables with Experiment's fields)."""
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise ValueError(f"cannot read experiments from {path}: {exc}") from None
    tables = data.get("experiment")
    if not isinstance(tables, list) or not tables or not all(isinstance(t, dict) for t in tables):
        raise ValueError(f"{path}: expected one or more [[experiment]] tables")
    known = {f.name for f in fields(Experiment)}
    out = []
    for t in tables:
        unknown = sorted(set(t) - known)
        if unknown:
            raise ValueError(f"{path}: unknown experiment field(s) {', '.join(unknown)} "
                             f"(known: {', '.join(sorted(known))})")
        try:
            out.append(Experiment(**t))
        except (TypeError, ValueError) as exc:
            raise ValueError(f"{path}: {exc}") from None
    names = [e.name for e in out]
    if len(set(names)) != len(names):
        raise ValueError(f"{path}: experiment names must be unique")
    return out


def cases_for(experiments: list[Experiment], piles=PILES, p_traj_pct=P_TRAJ_PCT,
              positions: int = N_POSITIONS) -> list[Case]:
    """One case per (experiment, pile, P_traj), the experiment's fields in the case (so the cache key
    changes when a configuration does). `positions` < 20 takes that many, spread
    over the 20 (`servo_positions`), for a quick look."""
    if not 1 <= positions <= N_POSITIONS:
        raise ValueError(f"servo positions must be 1-{N_POSITIONS}, got {positions}")
    return [Case.make(e.name, pile=pile, p_traj_pct=float(p), positions=positions, version=SWEEP_VERSION, **asdict(e))
            for e in experiments for pile in piles for p in p_traj_pct]


def servo_positions(n: int) -> list[int]:
    """n of the 20 initial positions, evenly spread (2 -> the same phase in both directions)."""
    return [round(i * N_POSITIONS / n) for i in range(n)]


def experiment_of(case: Case) -> Experiment:
    return Experiment(**{f.name: case.get(f.name) for f in fields(Experiment)})


# ----- running one case --------------------------------------------------------------------------

@dataclass(frozen=True)
class _IdealFlight:
    """The ideal plant's flight with FlownMission's interface (no energy: it has no motors)."""

    mission: Mission

    @property
    def _plant(self) -> IdealPlant:
        return IdealPlant(self.mission, StorageFrame())

    @property
    def duration_s(self) -> float:
        return self._plant.duration_s

    def trajectory_at(self, t_s: np.ndarray):
        return self._plant.states(t_s)

    energy_j = None
    completed = True


def _flight(e: Experiment, p_pct: float, cache_dir: Path) -> FlownMission | _IdealFlight:
    cfg = FlyConfig(mission=e.mission(p_pct))
    if e.plant == "ideal":
        return _IdealFlight(cfg.mission)
    return cached(cache_dir, e.flight_key(p_pct),
                  lambda: fly_mission(cfg.mission, cfg.frame, payload_kg=e.payload_kg))


def run_case(case: Case, cache_dir: str | Path = "runs/sweep-cache") -> list[dict]:
    """Rows of one case: one per servo position (and noise draw) for the 1D LiDAR, one for 2D/3D.
    Flights are cached under cache_dir (give workers a shared directory)."""
    cache_dir = Path(cache_dir)
    e = experiment_of(case)
    pile_name, p_pct = case.get("pile"), case.get("p_traj_pct")
    t0 = time.perf_counter()
    flown = _flight(e, p_pct, cache_dir)
    if not flown.completed:
        raise RuntimeError(f"{e.name}, P_traj {p_pct} %: the vehicle did not complete the mission")
    base = FlyConfig(mission=e.mission(p_pct), stockpile=pile_name, waveform=e.waveform)
    storage = base.mission.storage
    pile = paper_pile(pile_name, storage)
    common = {"energy_j": flown.energy_j, "flight_s": flown.duration_s, "true_volume_m3": pile.volume_m3}
    if e.sensor != "1d":
        rows = [_scanner_row(e, flown, base, pile)]
    else:
        world = World(storage, pile, base.lidar.max_range_m)
        t = np.arange(int(flown.duration_s * base.lidar.rate_hz) + 1) / base.lidar.rate_hz
        traj = flown.trajectory_at(t)
        rows = []
        for k in servo_positions(case.get("positions", N_POSITIONS)):
            cfg = replace(base, initial_position=k)
            wf = cfg.servo_waveform()
            for draw in range(max(1, e.noise_draws)):
                noise = SensorNoise.of(SensorNoiseModel.APPENDIX_A, cfg.lidar) if e.noise_draws else None
                samples = sample_flight(traj, wf, world, cfg.lidar, cfg.lever_arm_body_m, cfg.frame, noise=noise,
                                        seed=[int(p_pct), int(pile_name), k, draw])
                header = log_header(replace(cfg, sensor_noise=noise.model) if noise else cfg, wf)
                sv = survey_from_samples(samples, header, storage, cfg.frame, np.array(cfg.lever_arm_body_m),
                                         ReportOptions(plots=False))
                rows.append({"position": k, "draw": draw, **_metrics(sv, pile.volume_m3),
                             "n_points": len(sv.pile_points_w)})
    elapsed = time.perf_counter() - t0
    return [{**r, **common, "case_s": elapsed / len(rows)} for r in rows]


SWEPT_POLICIES = (DEFAULT_EMPTY_CELLS, *(p for p in EMPTY_CELL_POLICIES if p not in CONTACT_POLICIES))
"""The empty-cell policies each case's Ve is given under: the default, as the survey filled it, and those `fill_empty`
can apply to the fitted heights alone. The other contact policies need the cloud's wall contacts and the beams'
shadows, which `fill_empty` alone cannot see (each would give another policy's figure under its own name)."""


def _metrics(sv, true_m3: float) -> dict:
    """Ve under each empty-cell policy (`SWEPT_POLICIES`): the default's is the survey's heights as the report
    filled them, the others' the points' own fit over their hull filled again (`Survey.heights_hull`: before the
    `wall-strip` rule left strip cells to its fill, which those policies do not)."""
    own = sv.heights_fit if sv.heights_hull is None else sv.heights_hull
    out = {f"ve_{pol}_pct": volume_error_pct(grid_volume(
        sv.heights if pol == DEFAULT_EMPTY_CELLS else fill_empty(own, pol), sv.grid), true_m3)
        for pol in SWEPT_POLICIES}
    out["ra_pct"] = reconstructed_ratio_pct(sv.heights_fit)
    out["cells_clipped"] = sv.n_cells_clipped
    return out


def _scanner_row(e: Experiment, flown: FlownMission, base: FlyConfig, pile) -> dict:
    """One 2D/3D survey: the scan streamed in chunks into the ground station's fixed-size bins."""
    from ground.binning import HeightBinner, survey_from_points
    from ground.pointcloud import SensorErrorModel
    from sitl.sensing.scanners import HOKUYO_UTM_30LX, VELODYNE_PUCK_LITE, scan_flight

    spec = HOKUYO_UTM_30LX if e.sensor == "2d" else VELODYNE_PUCK_LITE
    storage = base.mission.storage
    world = World(storage, pile, spec.max_range_m)
    binner = HeightBinner(storage, SensorErrorModel(range_sigma_m=spec.range_sigma_m))
    n = 0
    for chunk in scan_flight(flown.trajectory_at, flown.duration_s, spec, world, base.lever_arm_body_m, base.frame):
        binner.add(chunk.points_w, chunk.range_m, chunk.dirs_w)
        n += len(chunk.range_m)
    sv = survey_from_points(binner, storage, ReportOptions(plots=False))
    return {"position": -1, "draw": 0, **_metrics(sv, pile.volume_m3), "n_points": n}
