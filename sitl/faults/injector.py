"""Fault injection for firmware-in-the-loop runs: what real flights break, on the simulated clock.

Modelled on ArduPilot's `SIM_*` parameters: every fault is a setting of `FaultSpec`, driven by
simulated time (seconds from the start of the survey) and one seed, so a (spec, seed) pair replays
exactly. `FaultInjector` applies a spec to the lockstep SITL's parts (`sitl.runners.lockstep_payload`):

- MAVLink link, both directions: packet loss, duplication, reordering, an outage window, added
  latency and jitter (a serial link keeps its order: jitter delays what follows too);
- the autopilot: a reboot (silent for a while, then `time_boot_ms` restarts from 0 and the message
  rates it was asked for are forgotten);
- the companion computer: its wall clock jumps (an NTP step or an RTC-less boot setting the time);
  the payload times samples on the monotonic clock, so only wall-clock users see it (MAVLink signing
  timestamps, log labels);
- the LIDAR-Lite: I2C NACK rate, stuck busy for a window, a power glitch (registers back to their
  power-on values), garbage reads, and glitch readings (a spurious maximum range or 1 cm);
- the TFMini: frames with a bad checksum, garbage bytes on the line, the sensor unplugged from its
  UART for a window (or for good: a duration of `inf`);
- the servo: stuck at some instant (the shaft stops; pulses keep going out), slow (the real servo
  slews slower than its calibration says), delayed (a dead time before it answers a pulse);
- the payload process: a power cut at some instant (the log keeps what was written by then);
- the companion's disk: full from some instant (a write takes what fits, then fails with ENOSPC).
"""

from __future__ import annotations

import collections
import errno
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, fields, replace

import numpy as np

from firmware_py.core.frames import Boresight

GLITCH_RANGE_M = 40.0
"""A glitch "maximum range" reading: the LIDAR-Lite's rated range, whatever the beam points at."""


def _window(name: str, w: tuple[float, float] | None) -> None:
    if w is None:
        return
    if len(w) != 2 or not all(math.isfinite(v) for v in w) or w[0] < 0 or w[1] <= 0:
        raise ValueError(f"fault {name} must be (start s >= 0, duration s > 0), got {w!r}")


MOUNT_FAULTS = frozenset({"servo_offset_deg", "servo_scale_pct", "boresight_deg", "sweep_yaw_deg"})
"""Faults of the mounting alone (where the shaft and the beam truly point): geometry, not timing or a device's
behaviour, so the batch payload flies them too (`sitl.sensing.batch_sampler.sample_flight`)."""

PAIRS = {"link_outage": "START,DURATION", "lidar_stuck_busy": "START,DURATION",
         "autopilot_reboot": "AT,SILENT_S", "clock_jump": "AT,JUMP_S", "tfmini_unplug": "AT,DURATION"}
"""The faults given as two numbers (the CLI's `NAME=A,B`)."""


def fault_syntax(names: list[str] | None = None) -> str:
    """The --fault forms, `NAME=X` or `NAME=A,B`, of every fault (or of `names`), in FaultSpec's order: the help
    texts list them from here, so a fault added to FaultSpec is never missing from them."""
    known = [f.name for f in fields(FaultSpec) if f.name != "seed"]
    return ", ".join(f"{n}={PAIRS.get(n, 'X')}" for n in known if names is None or n in names)


@dataclass(frozen=True)
class FaultSpec:
    """One run's faults (all off by default). Times are seconds from the start of the survey."""

    seed: int = 0
    link_loss_pct: float = 0.0
    link_dup_pct: float = 0.0
    link_reorder_pct: float = 0.0
    link_outage: tuple[float, float] | None = None
    link_latency_ms: float = 0.0
    link_jitter_ms: float = 0.0
    autopilot_reboot: tuple[float, float] | None = None
    clock_jump: tuple[float, float] | None = None
    i2c_nack_pct: float = 0.0
    lidar_stuck_busy: tuple[float, float] | None = None
    lidar_power_glitch_at_s: float | None = None
    lidar_garbage_pct: float = 0.0
    lidar_glitch_pct: float = 0.0
    tfmini_bad_frame_pct: float = 0.0  # frames sent with a wrong checksum
    tfmini_garbage_pct: float = 0.0  # frames followed by a few random bytes
    tfmini_unplug: tuple[float, float] | None = None  # (at s, for s; inf: never put back)
    servo_stuck_at_s: float | None = None
    servo_slow_factor: float = 1.0
    servo_delay_ms: float = 0.0
    servo_offset_deg: float = 0.0  # the true shaft sits this far from where the calibration puts it
    servo_scale_pct: float = 0.0  # ... and turns this much more per commanded radian
    boresight_deg: float = 0.0  # the LiDAR tilted this far out of the sweep plane (leaning forward)
    sweep_yaw_deg: float = 0.0  # the servo axis turned this far about body z
    power_cut_at_s: float | None = None
    disk_full_at_s: float | None = None

    def __post_init__(self) -> None:
        for f in ("link_loss_pct", "link_dup_pct", "link_reorder_pct", "i2c_nack_pct", "lidar_garbage_pct",
                  "lidar_glitch_pct", "tfmini_bad_frame_pct", "tfmini_garbage_pct"):
            v = getattr(self, f)
            if not (isinstance(v, int | float) and math.isfinite(v) and 0.0 <= v <= 100.0):
                raise ValueError(f"fault {f} must be a percentage 0-100, got {v!r}")
        _window("link_outage", self.link_outage)
        _window("lidar_stuck_busy", self.lidar_stuck_busy)
        _window("autopilot_reboot", self.autopilot_reboot)  # (at s, silent s)
        u = self.tfmini_unplug
        if u is not None and (len(u) != 2 or not math.isfinite(u[0]) or u[0] < 0 or math.isnan(u[1]) or u[1] <= 0):
            raise ValueError(f"fault tfmini_unplug must be (at s >= 0, duration s > 0 or inf), got {u!r}")
        for f, top in (("link_latency_ms", 10_000.0), ("link_jitter_ms", 10_000.0), ("servo_delay_ms", 1_000.0)):
            v = getattr(self, f)
            if not (isinstance(v, int | float) and math.isfinite(v) and 0.0 <= v <= top):
                raise ValueError(f"fault {f} must be 0-{top:g} ms, got {v!r}")
        if self.clock_jump is not None:
            c = self.clock_jump
            if len(c) != 2 or not all(math.isfinite(v) for v in c) or c[0] < 0 or c[1] == 0 or abs(c[1]) > 86_400:
                raise ValueError(f"fault clock_jump must be (at s >= 0, jump s != 0, |jump| <= 1 day), got {c!r}")
        for f in ("lidar_power_glitch_at_s", "servo_stuck_at_s", "power_cut_at_s", "disk_full_at_s"):
            v = getattr(self, f)
            if v is not None and not (math.isfinite(v) and v >= 0):
                raise ValueError(f"fault {f} must be a time >= 0 s, got {v!r}")
        for f, top in (("servo_offset_deg", 20.0), ("servo_scale_pct", 30.0), ("boresight_deg", 20.0),
                       ("sweep_yaw_deg", 20.0)):
            v = getattr(self, f)
            if not (isinstance(v, int | float) and math.isfinite(v) and abs(v) <= top):
                raise ValueError(f"fault {f} must be within +-{top:g}, got {v!r}")
        if not (math.isfinite(self.servo_slow_factor) and 0.05 <= self.servo_slow_factor <= 1.0):
            raise ValueError(f"fault servo_slow_factor must be in [0.05, 1] (1 = as calibrated), "
                             f"got {self.servo_slow_factor!r}")

    @property
    def mount_only(self) -> bool:
        """Every active fault is one of the mounting's (MOUNT_FAULTS)."""
        return set(self.active) <= MOUNT_FAULTS

    @property
    def servo_gain(self) -> float:
        """The true shaft's radians per radian the calibration says."""
        return 1.0 + self.servo_scale_pct / 100.0

    @property
    def servo_offset_rad(self) -> float:
        """Where the true shaft sits when the calibration says 0."""
        return math.radians(self.servo_offset_deg)

    @property
    def boresight(self) -> Boresight:
        """The beam's true mounting (square unless a boresight fault is set)."""
        return Boresight(math.radians(self.boresight_deg), math.radians(self.sweep_yaw_deg))

    @classmethod
    def parse(cls, items: list[str], seed: int = 0) -> FaultSpec:
        """From `NAME=VALUE` strings (the CLI's --fault): numbers, or `START,DURATION` for windows."""
        known = {f.name: f for f in fields(cls) if f.name != "seed"}
        values: dict = {}
        for item in items:
            name, sep, text = item.partition("=")
            name = name.strip().replace("-", "_")
            if not sep or name not in known:
                raise ValueError(f"bad fault {item!r}: expected NAME=VALUE with NAME one of {', '.join(known)}")
            try:
                nums = tuple(float(v) for v in text.split(","))
            except ValueError:
                raise ValueError(f"bad fault {item!r}: {text!r} is not a number (or START,DURATION)") from None
            pair = PAIRS.get(name)
            if len(nums) != (2 if pair else 1):
                raise ValueError(f"bad fault {item!r}: {name} takes " + (pair or "one number"))
            if name in values:  # the last one silently won before: which did the user mean?
                raise ValueError(f"fault {name} given twice ({item!r} after {name}={values[name]!r}): give it once")
            window = pair is not None
            values[name] = nums if window else nums[0]
        return cls(seed=seed, **values)

    @property
    def active(self) -> list[str]:
        """The faults this spec turns on (for tables and logs)."""
        default = FaultSpec()
        return [f.name for f in fields(self) if f.name != "seed" and getattr(self, f.name) != getattr(default, f.name)]

    def to_dict(self) -> dict:
        """For JSON (truth.json): a window that never ends has the duration None (JSON has no infinity)."""
        d = asdict(self)
        if self.tfmini_unplug is not None and math.isinf(self.tfmini_unplug[1]):
            d["tfmini_unplug"] = (self.tfmini_unplug[0], None)
        return d


class FaultyLink:
    """One direction of the MAVLink link, packet by packet: loss, duplication, reordering, outage.

    Wraps a `send_at(t_ns, data)` (the runner's delayed pipe); `survey_t0_ns` maps fault windows.
    """

    def __init__(self, send_at: Callable[[int, bytes], None], spec: FaultSpec, rng: np.random.Generator,
                 survey_t0_ns: Callable[[], int | None]) -> None:
        self._send_at, self.spec, self.rng, self._t0 = send_at, spec, rng, survey_t0_ns
        self._held: collections.deque[bytes] = collections.deque()
        self.counters = dict.fromkeys(("packets", "lost", "duplicated", "reordered", "outage_lost", "delayed"), 0)

    def _in_outage(self, t_ns: int) -> bool:
        t0, w = self._t0(), self.spec.link_outage
        if t0 is None or w is None:
            return False
        t = (t_ns - t0) / 1e9
        return w[0] <= t < w[0] + w[1]

    def send_at(self, t_ns: int, data: bytes) -> None:
        self.counters["packets"] += 1
        s, r = self.spec, self.rng
        if self._in_outage(t_ns):
            self.counters["outage_lost"] += 1
            return
        if s.link_loss_pct and r.random() * 100 < s.link_loss_pct:
            self.counters["lost"] += 1
            return
        if s.link_reorder_pct and not self._held and r.random() * 100 < s.link_reorder_pct:
            self._held.append(data)  # goes out after the next packet
            self.counters["reordered"] += 1
            return
        t_out = t_ns + self._delay_ns()
        self._send_at(t_out, data)
        while self._held:
            self._send_at(t_out, self._held.popleft())
        if s.link_dup_pct and r.random() * 100 < s.link_dup_pct:
            self._send_at(t_out, data)
            self.counters["duplicated"] += 1

    def _delay_ns(self) -> int:
        """Added latency plus uniform jitter; the pipe below keeps the order (a serial link)."""
        s = self.spec
        if not (s.link_latency_ms or s.link_jitter_ms):
            return 0
        ms = s.link_latency_ms + (self.rng.random() * s.link_jitter_ms if s.link_jitter_ms else 0.0)
        self.counters["delayed"] += 1
        return round(ms * 1e6)


class FaultInjector:
    """Applies a FaultSpec to one lockstep run; `tick(now_ns)` fires the timed faults."""

    def __init__(self, spec: FaultSpec) -> None:
        self.spec = spec
        self.rng = np.random.default_rng(spec.seed)
        self.survey_t0_ns: int | None = None
        self.counters: dict[str, int] = dict.fromkeys(("lidar_glitches", "power_glitches", "servo_stuck",
                                                       "autopilot_reboots", "clock_jumps", "tfmini_unplugs"), 0)
        self._lidar = self._bus = self._servo = self._tfmini = None
        self._stuck_done = self._glitch_done = self._servo_done = self._reboot_done = self._jump_done = False
        self.reboot: Callable[[float], None] | None = None  # set by the runner: reboot the autopilot, silent s
        self.wall_offset_s = 0.0  # the companion's wall clock minus the true time (the clock_jump fault)

    # -- wiring -------------------------------------------------------------------------------------
    def link(self, send_at: Callable[[int, bytes], None]) -> FaultyLink:
        return FaultyLink(send_at, self.spec, np.random.default_rng(self.rng.integers(2**63)),
                          lambda: self.survey_t0_ns)

    def range_at(self, true_range_at: Callable[[int], float | None]) -> Callable[[int], float | None]:
        """The emulator's view of the world, with glitch readings mixed in."""
        p = self.spec.lidar_glitch_pct / 100.0
        if p <= 0:
            return true_range_at
        rng = np.random.default_rng(self.rng.integers(2**63))

        def glitchy(t_ns: int) -> float | None:
            if rng.random() < p:
                self.counters["lidar_glitches"] += 1
                return GLITCH_RANGE_M if rng.random() < 0.5 else 0.01
            return true_range_at(t_ns)
        return glitchy

    def attach(self, bus, lidar, servo) -> None:
        """The simulated I2C bus, the emulated LIDAR-Lite and the emulated servo of the run."""
        self._bus, self._lidar, self._servo = bus, lidar, servo
        if self.spec.i2c_nack_pct:
            bus.rng = np.random.default_rng(self.rng.integers(2**63))
            bus.nack_probability = self.spec.i2c_nack_pct / 100.0
        if self.spec.lidar_garbage_pct:
            lidar.rng = np.random.default_rng(self.rng.integers(2**63))
            lidar.garbage_reads = self.spec.lidar_garbage_pct / 100.0
        if self.spec.servo_slow_factor != 1.0:
            slow = replace(servo.cal, slew_rad_s=servo.cal.slew_rad_s * self.spec.servo_slow_factor)
            servo.cal = slow
            servo.model.cal = slow
        if self.spec.servo_delay_ms:
            servo.delay_ns = round(self.spec.servo_delay_ms * 1e6)
        if self.spec.servo_offset_deg or self.spec.servo_scale_pct:
            # true angle = (1 + s) * calibrated angle + offset: the pulse-to-angle map of the real part
            scale, cal = self.spec.servo_gain, servo.cal
            true = replace(cal, us_per_rad=cal.us_per_rad / scale,
                           center_us=cal.center_us - self.spec.servo_offset_rad * cal.us_per_rad / scale)
            servo.cal = true
            servo.model.cal = true

    def attach_tfmini(self, port) -> None:
        """The emulated TFMini of the run (`EmulatedTfminiPort` or `PtyTfmini`: its frame source and its
        `unplugged` switch)."""
        self._tfmini = port
        src = port.source
        if self.spec.tfmini_bad_frame_pct or self.spec.tfmini_garbage_pct:
            src.rng = np.random.default_rng(self.rng.integers(2**63))
            src.bad_frames = self.spec.tfmini_bad_frame_pct / 100.0
            src.garbage = self.spec.tfmini_garbage_pct / 100.0

    @property
    def boresight(self) -> Boresight:
        """The beam's true mounting (`FaultSpec.boresight`)."""
        return self.spec.boresight

    def wall_clock(self, true_wall_s: Callable[[], float]) -> Callable[[], float]:
        """The companion's wall clock (Unix s) as the payload reads it: the true one, plus any jump."""
        return lambda: true_wall_s() + self.wall_offset_s

    def start_survey(self, now_ns: int) -> None:
        self.survey_t0_ns = now_ns

    def t_s(self, now_ns: int) -> float | None:
        return None if self.survey_t0_ns is None else (now_ns - self.survey_t0_ns) / 1e9

    def tick(self, now_ns: int) -> None:
        t = self.t_s(now_ns)
        if t is None:
            return
        s = self.spec
        if s.lidar_stuck_busy is not None and self._lidar is not None:
            a, d = s.lidar_stuck_busy
            self._lidar.stuck_busy = a <= t < a + d
        if s.tfmini_unplug is not None and self._tfmini is not None:
            a, d = s.tfmini_unplug
            out = a <= t < a + d
            if out and not self._tfmini.unplugged:
                self.counters["tfmini_unplugs"] += 1
            self._tfmini.unplugged = out
        if s.lidar_power_glitch_at_s is not None and not self._glitch_done and t >= s.lidar_power_glitch_at_s:
            self._lidar.power_glitch()
            self._glitch_done = True
            self.counters["power_glitches"] += 1
        if s.autopilot_reboot is not None and not self._reboot_done and t >= s.autopilot_reboot[0]:
            if self.reboot is not None:
                self.reboot(s.autopilot_reboot[1])
            self._reboot_done = True
            self.counters["autopilot_reboots"] += 1
        if s.clock_jump is not None and not self._jump_done and t >= s.clock_jump[0]:
            self.wall_offset_s += s.clock_jump[1]
            self._jump_done = True
            self.counters["clock_jumps"] += 1
        if s.servo_stuck_at_s is not None and not self._servo_done and t >= s.servo_stuck_at_s:
            self._servo.stuck = True
            self._servo_done = True
            self.counters["servo_stuck"] += 1

    def opener(self, clock_ns: Callable[[], int]) -> Callable[[str, str], DiskFullFile]:
        """A SampleLogWriter opener whose file fills up at disk_full_at_s (see DiskFullFile)."""
        def full() -> bool:
            t = self.t_s(clock_ns())
            return t is not None and self.spec.disk_full_at_s is not None and t >= self.spec.disk_full_at_s
        return lambda path, mode: DiskFullFile(open(path, mode), full)  # the writer closes it

    def power_cut_due(self, now_ns: int) -> bool:
        t = self.t_s(now_ns)
        return t is not None and self.spec.power_cut_at_s is not None and t >= self.spec.power_cut_at_s


class DiskFullFile:
    """A file on a disk that fills up: once `full()`, a write stores half of what it was given (a
    real full disk can take part of a write) and fails with ENOSPC, as do all later ones."""

    def __init__(self, f, full: Callable[[], bool]) -> None:
        self._f, self._full = f, full
        self.failed_writes = 0

    def write(self, data) -> int:
        if self._full():
            if not self.failed_writes:
                self._f.write(bytes(data)[: len(data) // 2])
            self.failed_writes += 1
            raise OSError(errno.ENOSPC, "No space left on device")
        return self._f.write(data)

    def __getattr__(self, name: str):
        return getattr(self._f, name)


def wrongly_tagged(records: np.ndarray, true_t_s: np.ndarray, true_states: np.ndarray, *, pos_tol_m: float = 0.10,
                   att_tol_rad: float = math.radians(1.0)) -> np.ndarray:
    """Samples logged unflagged whose pose is not the vehicle's true pose at their time.

    The tolerances are what a correct tag can miss by: interpolation between 50 Hz poses over a
    lossy link and the time-sync error (about a centimetre and a tenth of a degree here); a sample
    tagged with an old pose misses by the distance flown meanwhile (1 m/s: 10 cm per 100 ms).
    """
    from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD

    ok = (records["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0
    r = records[ok]
    t = r["t_s"].astype(float)
    truth = np.column_stack([np.interp(t, true_t_s, true_states[k]) for k in ("north_m", "east_m", "down_m")])
    pos_err = np.linalg.norm(np.column_stack([r["x_m"], r["y_m"], r["z_m"]]) - truth, axis=1)
    att_err = np.zeros(len(r))
    for name in ("roll_rad", "pitch_rad", "yaw_rad"):
        true_a = np.interp(t, true_t_s, np.unwrap(true_states[name]))
        d = (r[name].astype(float) - true_a + np.pi) % (2 * np.pi) - np.pi
        att_err = np.maximum(att_err, np.abs(d))
    bad = np.zeros(len(records), dtype=bool)
    bad[np.flatnonzero(ok)] = (pos_err > pos_tol_m) | (att_err > att_tol_rad)
    return bad
