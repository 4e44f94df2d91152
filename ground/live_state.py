"""The running state behind `listen --web`'s live page: coverage, track and running volume, as records arrive.

Three threads, so the page can never slow the receiving down:

- the receiver (`ground.listen.Listener`, the main thread) only hands each batch of records over
  (`LiveState.offer`: a deque append, no lock, no computation);
- the accumulator thread (`LiveState.start`) takes the batches every `ACCUMULATE_PERIOD_S`, places
  their returns with the report's own eqs. (3)-(6) (`ground.pointcloud.cloud_from_samples`), removes
  walls and roof and bins the rest on the floor (`ground.binning.HeightBinner`: fixed memory however
  long the flight), and keeps the vehicle's track (decimated to at most `MAX_TRACK_POINTS`);
- the volume thread recomputes the volume and its 90 % interval from every record so far with the
  report's own computation (`ground.report.survey_from_samples` and `summarise`, without the slow
  self-calibration and servo re-timing), at most every `VOLUME_PERIOD_S` and never more than a third
  of the time (the next run waits twice as long as the last one took).

The page's HTTP thread reads `LiveState.snapshot()`: small copies under the accumulator's lock
(the receiver never takes it), serialised outside it, cached for `SNAPSHOT_CACHE_S`.

Without a usable header (no `--header`, or one without the storage geometry) there is no building
to place returns in: the state keeps the counters and the track in the autopilot's NED frame only,
and says why (`LiveState.geometry_problem`).
"""

from __future__ import annotations

import json
import math
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np

from firmware_py.core.cli import NoVolumeError, UserError
from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.header import header_boresight
from firmware_py.core.samplelog import UNPOSED, SampleLog
from firmware_py.core.storage import Storage
from ground.binning import HeightBinner
from ground.plausibility import PlausibilityLimits, implausible, without_implausible
from ground.pointcloud import Cloud, SensorErrorModel, cloud_from_samples
from ground.report import ReportOptions, header_geometry, summarise, survey_from_samples
from ground.surface import Grid

ACCUMULATE_PERIOD_S = 0.25
"""How often the accumulator takes the records handed over (the page polls once a second)."""
VOLUME_PERIOD_S = 3.0
"""Shortest time between two volume computations (docs/live.md: 0.26 s for 45,000 records)."""
VOLUME_DUTY = 3.0
"""After a volume computation of t seconds the next waits at least VOLUME_DUTY x t: at most a third of a core."""
MAX_VOLUME_RECORDS = 2_000_000
"""Records kept for the running volume (118 MB; 67 minutes at the payload's 500 Hz, longer than a battery);
later ones still feed the coverage map and the counters, and the page says the volume stopped growing."""
MAX_TRACK_POINTS = 5000
"""Track points kept; past it every other one is dropped and the spacing doubles (the whole flight stays)."""
TRACK_STEP_S = 0.1
"""Initial spacing of the track's points, in sample time."""
MAP_MAX_CELLS_SIDE = 120
"""The coverage map has at most this many cells along the building's length (a light JSON, a legible map)."""
MAP_MIN_CELL_M = 0.25
"""The map's cells are never finer than the report's default grid."""
STALE_AFTER_S = 3.0
"""No records for this long: the page says the stream stopped."""
SNAPSHOT_CACHE_S = 0.5
"""A snapshot is rebuilt at most this often, however many browsers poll."""
RATE_WINDOW_S = 3.0
"""The record rate is taken over this much of the recent past."""
LIVE_REPORT_OPTIONS = ReportOptions(plots=False, self_calibration=False, servo_retiming=False,
                                    pose_correction=False)
"""The report's computation for the running volume, less its slow estimates (the mount, the servo timing, the
pose correction: seconds each, on a survey not yet finished; the report after the flight makes them)."""


class VolumeState(Enum):
    """Where the running volume stands."""

    NO_GEOMETRY = "no-geometry"  # no usable header: no building, no volume
    WAITING = "waiting"  # no records yet
    NOT_YET = "not-yet"  # records, but too few for a surface (the reason is given)
    OK = "ok"


def map_cell_m(storage: Storage) -> float:
    """The coverage map's cell side: MAP_MAX_CELLS_SIDE cells along the longer side, at least MAP_MIN_CELL_M,
    rounded up to 5 cm."""
    side = max(storage.length_m, storage.width_m) / MAP_MAX_CELLS_SIDE
    return max(MAP_MIN_CELL_M, math.ceil(side / 0.05 - 1e-9) * 0.05)


@dataclass(frozen=True)
class LiveGeometry:
    """What the header says about where returns land: the building, its frame, the lever arm, the mount."""

    header: dict[str, Any] = field(repr=False)
    storage: Storage
    frame: StorageFrame
    lever_arm_body_m: tuple[float, float, float]
    boresight: Boresight

    @classmethod
    def from_header(cls, header: dict[str, Any], where: str) -> LiveGeometry:
        """The geometry of a log header; UserError (one line, naming `where`) when it lacks or garbles it."""
        log = SampleLog(header, np.empty(0), 0, 0, 0, 0)
        storage, frame, lever = header_geometry(log, where)  # the report's own reading and its errors
        return cls(header, storage, frame, (float(lever[0]), float(lever[1]), float(lever[2])),
                   header_boresight(header))


@dataclass(frozen=True)
class LiveOptions:
    """How the running state is kept (module docstring for each default)."""

    volume_period_s: float = VOLUME_PERIOD_S
    max_volume_records: int = MAX_VOLUME_RECORDS
    max_track_points: int = MAX_TRACK_POINTS
    report: ReportOptions = LIVE_REPORT_OPTIONS

    def __post_init__(self) -> None:
        if not (math.isfinite(self.volume_period_s) and self.volume_period_s > 0):
            raise ValueError(f"volume period must be > 0 s, got {self.volume_period_s!r}")
        if self.max_volume_records < 1 or self.max_track_points < 2:
            raise ValueError("the record and track caps must be positive")


@dataclass(frozen=True)
class VolumeResult:
    """One running-volume computation (the report's figures, and when and how long)."""

    state: VolumeState
    volume_m3: float | None = None
    interval_m3: tuple[float, float] | None = None
    coverage_ratio_pct: float | None = None
    n_points_used: int = 0
    records: int = 0
    computed_at: float | None = None  # monotonic
    compute_s: float | None = None
    why: str | None = None
    surface_z: tuple[float | None, ...] | None = None  # per map cell: the fitted surface's height; None: unseen


Counters = Callable[[], dict[str, Any]]
"""The receiver's counters for the page (records, datagrams, lost, ...): `Listener.counters`."""


class LiveState:
    """The live page's state (module docstring). `offer` from the receiver; `start`/`close` the workers;
    `snapshot` / `snapshot_json` from the page's server; `accumulate` / `compute_volume` run one step by hand.

    Args:
        geometry: the header's geometry; None: counters and track only (`geometry_problem` says why).
        counters: the receiver's counters (called from the page's thread: must only read).
        geometry_problem: why there is no geometry (shown on the page).
        opts: caps and periods.
        clock: monotonic seconds.
    """

    def __init__(self, geometry: LiveGeometry | None, counters: Counters, *, geometry_problem: str | None = None,
                 opts: LiveOptions | None = None, clock: Callable[[], float] = time.monotonic) -> None:
        self.geometry = geometry
        self.geometry_problem = geometry_problem
        self.opts = opts or LiveOptions()
        self._counters = counters
        self._clock = clock
        self._t0 = clock()
        self._inbox: deque[np.ndarray] = deque()  # the receiver appends, the accumulator pops: no lock needed
        self._last_records_at: float | None = None
        self._lock = threading.Lock()  # the accumulator's data vs the snapshot's copies (never the receiver)
        self._binner: HeightBinner | None = None
        self._limits: PlausibilityLimits | None = None
        if geometry is not None:
            self._limits = PlausibilityLimits.from_header(geometry.header, geometry.storage)
            self._binner = HeightBinner(geometry.storage, SensorErrorModel.from_header(geometry.header),
                                        bin_m=map_cell_m(geometry.storage))
        self._track: list[tuple[float, float]] = []
        self._track_step_s = TRACK_STEP_S
        self._track_next_t = -math.inf
        self._position: tuple[float, float, float] | None = None
        self._course_rad: float | None = None
        self._n_accumulated = 0
        self._n_points = 0
        self._volume_parts: list[np.ndarray] = []
        self._volume_records = 0
        self._volume_capped = False
        self._volume = VolumeResult(VolumeState.NO_GEOMETRY if geometry is None else VolumeState.WAITING,
                                    why=geometry_problem)
        self._volume_done_records = 0
        self._rate_hist: deque[tuple[float, int]] = deque()
        self._cache: tuple[float, bytes] | None = None
        self._cache_lock = threading.Lock()
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.worker_error: str | None = None  # the last error a worker survived (shown on the page)

    # ----- the receiver's side ------------------------------------------------------------------------

    def offer(self, records: np.ndarray, now: float | None = None) -> None:
        """Hand a batch of received records over (the receiver's only cost: an append)."""
        if len(records):
            self._inbox.append(records)
            self._last_records_at = self._clock() if now is None else now

    # ----- the workers --------------------------------------------------------------------------------

    def start(self) -> None:
        """Start the accumulator and (with a geometry) the volume thread; daemons, stopped by `close`."""
        if self._threads:
            return
        targets = [self._accumulate_loop] + ([self._volume_loop] if self.geometry is not None else [])
        for target in targets:
            t = threading.Thread(target=target, name=f"live-{target.__name__.strip('_')}", daemon=True)
            t.start()
            self._threads.append(t)

    def close(self) -> None:
        """Stop the workers (a volume computation under way finishes first, at most a few seconds)."""
        self._stop.set()
        for t in self._threads:
            t.join(timeout=30.0)
        self._threads.clear()

    def _accumulate_loop(self) -> None:
        while not self._stop.wait(ACCUMULATE_PERIOD_S):
            self._survive(self.accumulate)

    def _volume_loop(self) -> None:
        wait = self.opts.volume_period_s
        while not self._stop.wait(wait):
            if self._volume_records == self._volume_done_records:
                wait = ACCUMULATE_PERIOD_S  # nothing new: look again soon
                continue
            took = self._survive(self.compute_volume)
            wait = max(self.opts.volume_period_s, VOLUME_DUTY * (took or 0.0))

    def _survive(self, step: Callable[[], Any]) -> Any:
        """One step of a worker: an error it meets (a forged datagram's records, a bug) is kept for the page
        and the worker goes on; the receiver is never concerned, nothing is printed over the status line."""
        try:
            with np.errstate(all="ignore"):  # NaN and overflow in records are the checks' business, not stderr's
                return step()
        except Exception as exc:  # a worker thread must outlive one bad batch (docs/design-notes.md)
            self.worker_error = f"{type(exc).__name__}: {exc}"[:300]
            return None

    def accumulate(self) -> int:
        """Take every batch handed over so far into the map, the track and the volume's records; how many."""
        parts = []
        while self._inbox:
            parts.append(self._inbox.popleft())
        now = self._clock()
        n_received = int(self._counters().get("records", 0))
        with self._lock:
            self._rate_hist.append((now, n_received))
            while len(self._rate_hist) > 2 and now - self._rate_hist[1][0] >= RATE_WINDOW_S:
                self._rate_hist.popleft()
        if not parts:
            return 0
        recs = np.concatenate(parts)
        geo = self.geometry
        if geo is not None:  # records no sensor, sweep or building could give (the report's own limits) go
            recs = without_implausible(recs, implausible(recs, self._limits, geo.frame))
        pos_ned = np.column_stack([recs["x_m"], recs["y_m"], recs["z_m"]]).astype(float)
        # The track: poses the payload vouched for (a record without a fresh pose carries none worth drawing).
        finite = (np.isfinite(pos_ned).all(axis=1) & np.isfinite(recs["t_s"])
                  & ((recs["flags"] & int(UNPOSED)) == 0))
        if geo is None:
            cloud = None
            pos = pos_ned[finite] * np.array([1.0, 1.0, -1.0])  # north, east, up
            course = recs["yaw_rad"][finite].astype(float)  # clockwise from north
        else:
            cloud = cloud_from_samples(recs, np.asarray(geo.lever_arm_body_m), geo.frame, boresight=geo.boresight)
            w = geo.frame.ned_to_w(pos_ned[finite])
            inside = np.all((w >= self._limits.pose_lo_w_m) & (w <= self._limits.pose_hi_w_m), axis=1)
            finite[np.flatnonzero(finite)[~inside]] = False  # the track too: only poses within the limits
            pos = w[inside]
            course = geo.frame.heading_rad - recs["yaw_rad"][finite].astype(float)  # W: anticlockwise from x
        with self._lock:
            if cloud is not None:
                self._add_cloud(cloud)
                if not self._volume_capped:
                    room = self.opts.max_volume_records - self._volume_records
                    take = recs[:room]
                    self._volume_parts.append(take)
                    self._volume_records += len(take)
                    self._volume_capped = len(take) < len(recs)
            self._add_track(recs["t_s"][finite], pos, course)
            self._n_accumulated += len(recs)
        return len(recs)

    def _add_cloud(self, cloud: Cloud) -> None:
        if len(cloud.points_w):
            self._binner.add(cloud.points_w, cloud.range_m, cloud.dirs_w)
            self._n_points += len(cloud.points_w)

    def _add_track(self, t_s: np.ndarray, pos: np.ndarray, course: np.ndarray) -> None:
        if not len(pos):
            return
        self._position = (float(pos[-1, 0]), float(pos[-1, 1]), float(pos[-1, 2]))
        c = float(course[-1])
        self._course_rad = c if math.isfinite(c) else None
        for t, p in zip(t_s, pos, strict=True):  # a batch is a few hundred records at most: cheap
            if t >= self._track_next_t:
                self._track.append((float(p[0]), float(p[1])))
                self._track_next_t = t + self._track_step_s
        if len(self._track) > self.opts.max_track_points:
            self._track = self._track[::2]
            self._track_step_s *= 2.0

    def compute_volume(self) -> float:
        """The volume and its interval from every record kept, by the report's computation; seconds it took."""
        geo = self.geometry
        if geo is None:
            return 0.0
        parts = list(self._volume_parts)  # a list copy: the accumulator only appends
        n = sum(len(p) for p in parts)
        t0 = self._clock()
        if n == 0:
            self._volume = VolumeResult(VolumeState.WAITING)
            return 0.0
        samples = np.concatenate(parts)
        try:
            survey = survey_from_samples(samples, geo.header, geo.storage, geo.frame,
                                         np.asarray(geo.lever_arm_body_m), self.opts.report)
            if not np.isfinite(survey.heights_fit).any():  # where the report says "no volume"
                raise NoVolumeError(f"no surface could be fitted from {len(survey.pile_points_w)} point(s) on the "
                                    f"stockpile so far ({n} records)")
            rep = summarise(survey, SampleLog(geo.header, samples, 0, 0, 0, 0), self.opts.report, None)
        except (NoVolumeError, UserError, ValueError) as exc:  # too few points for a surface, so far
            took = self._clock() - t0
            self._volume = VolumeResult(VolumeState.NOT_YET, records=n, computed_at=t0 + took, compute_s=took,
                                        why=str(exc))
        else:
            surface = self._surface_on_map(survey.heights_fit, survey.grid)
            took = self._clock() - t0
            iv = rep["volume_interval_m3"]
            self._volume = VolumeResult(VolumeState.OK, volume_m3=float(rep["volume_m3"]),
                                        interval_m3=None if iv is None else (float(iv[0]), float(iv[1])),
                                        coverage_ratio_pct=float(rep["coverage_ratio_pct"]),
                                        n_points_used=int(rep["n_points_used"]), records=n,
                                        computed_at=t0 + took, compute_s=took, surface_z=surface)
        self._volume_done_records = n
        return took

    def _surface_on_map(self, heights_fit: np.ndarray, grid: Grid) -> tuple[float | None, ...]:
        """The fitted surface on the map's cells: the mean height of the report cells centred in each, None
        where most of them are unreconstructed (the cells R_a misses: unseen so far)."""
        nx, ny = self._binner.shape
        xc, yc = grid.centres()
        ix = np.clip((xc * (nx / grid.length_m)).astype(np.int64), 0, nx - 1)
        iy = np.clip((yc * (ny / grid.width_m)).astype(np.int64), 0, ny - 1)
        flat = (ix * ny + iy).ravel()
        h = heights_fit.ravel()
        ok = np.isfinite(h)
        total = np.bincount(flat, minlength=nx * ny)
        known = np.bincount(flat[ok], minlength=nx * ny)
        z_sum = np.bincount(flat[ok], weights=h[ok], minlength=nx * ny)
        seen = (known > 0) & (2 * known >= total)
        return tuple(round(float(z_sum[k] / known[k]), 2) if seen[k] else None for k in range(nx * ny))

    # ----- the page's side ----------------------------------------------------------------------------

    def snapshot(self) -> dict[str, Any]:
        """The page's state now (the JSON of /state.json; docs/live.md lists its fields)."""
        now = self._clock()
        counters = dict(self._counters())
        last = self._last_records_at
        since = None if last is None else max(0.0, now - last)
        geo = self.geometry
        with self._lock:  # copies only
            hist = list(self._rate_hist)
            track = list(self._track)
            position, course = self._position, self._course_rad
            n_points = self._n_points
            if self._binner is not None:
                count = self._binner.count.copy()
                sum_z = self._binner.sum_z.copy()
            capped, kept = self._volume_capped, self._volume_records
        rate = None
        if len(hist) >= 2 and hist[-1][0] > hist[0][0]:
            rate = (hist[-1][1] - hist[0][1]) / (hist[-1][0] - hist[0][0])
        vol = self._volume
        state: dict[str, Any] = {
            "elapsed_s": now - self._t0,
            "frame": "storage" if geo is not None else "ned",
            "geometry_problem": self.geometry_problem,
            "worker_error": self.worker_error,
            "counters": {**counters, "rate_hz": rate},
            "since_last_records_s": since,
            "stale": since is not None and since > STALE_AFTER_S,
            "stale_after_s": STALE_AFTER_S,
            "track": [[round(x, 2), round(y, 2)] for x, y in track],
            "position": None if position is None else [round(v, 2) for v in position],
            "course_rad": None if course is None else round(course, 3),
            "storage": None if geo is None else geo.storage.to_dict(),
            "map": None,
            "volume": {"state": vol.state.value, "volume_m3": vol.volume_m3,
                       "interval_m3": None if vol.interval_m3 is None else list(vol.interval_m3),
                       "coverage_ratio_pct": vol.coverage_ratio_pct, "n_points_used": vol.n_points_used,
                       "records": vol.records, "records_kept": kept, "capped": capped,
                       "age_s": None if vol.computed_at is None else max(0.0, now - vol.computed_at),
                       "compute_s": vol.compute_s, "why": vol.why},
        }
        if geo is not None:
            nx, ny = self._binner.shape
            seen = count > 0
            z = np.full(count.shape, np.nan)
            z[seen] = sum_z[seen] / count[seen]
            surface = vol.surface_z
            unseen = ~seen if surface is None else np.array([v is None for v in surface]) & ~seen
            state["map"] = {"nx": nx, "ny": ny, "cell_m": self._binner.bin_m,
                            "z_m": [None if not s else round(float(v), 2) for s, v in zip(seen, z, strict=True)],
                            "surface_z_m": None if surface is None else list(surface),
                            "points_pct": 100.0 * float(seen.mean()), "unseen_pct": 100.0 * float(unseen.mean()),
                            "n_points": n_points}
        return state

    def snapshot_json(self) -> bytes:
        """`snapshot` as UTF-8 JSON, rebuilt at most every SNAPSHOT_CACHE_S."""
        with self._cache_lock:
            now = self._clock()
            if self._cache is not None and now - self._cache[0] < SNAPSHOT_CACHE_S:
                return self._cache[1]
            body = json.dumps(self.snapshot(), allow_nan=False, separators=(",", ":")).encode()
            self._cache = (now, body)
            return body
