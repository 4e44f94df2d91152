"""Garmin LIDAR-Lite v3 over I2C, written against the HAL's I2CBus and Clock.

The part (Garmin's LIDAR-Lite v3 Operation Manual and Technical Specifications):

- 7-bit address 0x62, 400 kHz max. Register reads are SPLIT transfers: write the register address
  (STOP), then a separate read. The part does not support a repeated START (the v3 manual, as
  quoted in garmin/LIDARLite_Arduino_Library issue #17; ArduPilot's PulsedLightLRF sets
  `set_split_transfers(true)`; on a Pi kernel doing combined transfers it reads 255), so this
  driver never calls `I2CBus.write_read`.
- Measure: write 0x04 (with receiver bias correction) or 0x03 (without) to ACQ_COMMAND 0x00.
  Bias correction is needed "periodically (e.g. 1 out of every 100 readings)" (Garmin's library).
  STATUS 0x01 bit 0 is busy; then 2 bytes from 0x8f = FULL_DELAY_HIGH 0x0f | 0x80 (the
  auto-increment bit) give the distance in cm, big-endian. 1 cm (and 0) means no valid return.
- Reset: write 0x00 to 0x00; the part reloads its defaults in about 22 ms.

Unlike Garmin's and Adafruit's libraries, every busy-poll has a deadline, no result is a sentinel
distance (a `Reading` carries a `ReadStatus`), and no I2C error is swallowed: it becomes a
BUS_ERROR reading, is counted, and is kept in `last_error`. The PX4/ArduPilot lore is kept: reset
after a run of zero readings or errors (PX4 ll40ls: 20 zeros), and read the configuration
registers back periodically, re-applying them when a power glitch has reset the part (ArduPilot's
checked registers).

Timing model (used for the presets' documented times, the default busy deadline, and by
sitl.devices.lidarlite_emu so the emulator and these docs agree)::

    t_acq = 700 us + (n_signal + n_ref) * 21 us  (+ 200 us with receiver bias correction)

n_signal is at most SIG_COUNT_VAL (a strong return ends integration early; no return always uses
all of it), n_ref the reference acquisitions (5 by default, REF_COUNT_VAL when ACQ_CONFIG bit 2 is
set). The manual says "rate = 1/n and range = n^(1/4), where n is the number of acquisitions"
(SIG_COUNT_VAL) and specifies "update rate 270 Hz typical, 650 Hz fast mode, >1000 Hz short range
only". The affine fit puts the default (n = 128) at 3.49 ms, i.e. 270 Hz with ~0.2 ms of bus
traffic per cycle at 400 kHz; n = 29 (0x1d) at 1.41 ms, ~620 Hz; a strong short-range return
(n_signal ~ 1, 3 references) at 0.78 ms, ~1000 Hz. The bias-correction cost is an assumption (Garmin's
library says only that measurements without it are faster). Range scales as 40 m * (n/128)^(1/4)
for a 70 % reflective target (the manual's 40 m at the default count).

Timestamps: `Reading.t_ns` is the acquisition-trigger time, read from the clock right after the
ACQ_COMMAND write returned (its STOP starts the acquisition). That is the instant the range belongs
to: the laser fires from then on, the completion time is only known to within a poll interval and
moves with bus load and scheduling, and a split loop may collect long after. The integration spans
the acquisition (1.2-1.4 ms in the fast preset), so its centroid lags the stamp by about half of
it: ~3 mrad of servo travel at the paper's 5 rad/s, inside the 8 mrad beam. The SITL's emulator
samples the true range at this same instant, so SITL stamps are exact.

Split measurement: `measure_start()` triggers and returns the trigger time at once;
`measure_finish()` polls busy (with the deadline) and reads the range. A loop can trigger at its
tick, do other work while the part integrates (log the previous sample, read MAVLink, command the
servo), then collect:

    t_ns = lidar.measure_start()
    ...other work, ~1 ms...
    reading = lidar.measure_finish()   # reading.t_ns == t_ns
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass, fields
from enum import IntFlag

from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.drivers.reading import Reading, ReadStatus  # the loop's types, also importable from here
from firmware_py.hal import Clock, I2CBus, I2CError

log = logging.getLogger(__name__)

DEFAULT_ADDRESS = 0x62

# Registers (manual's control register list).
_REG_ACQ_COMMAND = 0x00
_REG_STATUS = 0x01
_REG_SIG_COUNT_VAL = 0x02
_REG_ACQ_CONFIG_REG = 0x04
_REG_FULL_DELAY_HIGH = 0x0F
_REG_FULL_DELAY_LOW = 0x10  # read together with the high byte through the auto-increment address
_REG_THRESHOLD_BYPASS = 0x1C
_AUTO_INCREMENT = 0x80
_REG_DISTANCE = _REG_FULL_DELAY_HIGH | _AUTO_INCREMENT  # 0x8f: high byte, then 0x10 low byte

# ACQ_COMMAND values.
_CMD_RESET = 0x00
_CMD_MEASURE = 0x03  # without receiver bias correction
_CMD_MEASURE_BIAS = 0x04  # with receiver bias correction

# Timing and range model (module docstring).
T_ACQ_FIXED_NS = 700_000
T_ACQ_PER_COUNT_NS = 21_000
T_BIAS_CORRECTION_NS = 200_000
DEFAULT_REF_COUNT = 5
DEFAULT_SIG_COUNT = 0x80
RANGE_AT_DEFAULT_COUNT_M = LIDARLITE_V3.max_range_m
"""The datasheet's 40 m (70 % reflective target) at the default count: one number, in core.sensor."""
RESET_TIME_NS = 22_000_000
"""The manual's re-initialisation time after a reset command."""


class StatusFlag(IntFlag):
    """STATUS register 0x01 bits (LIDAR-Lite v3)."""

    BUSY = 0x01
    REF_OVERFLOW = 0x02
    SIGNAL_OVERFLOW = 0x04
    INVALID_SIGNAL = 0x08  # no peak above the correlation noise floor: no valid return
    SECONDARY_RETURN = 0x10
    HEALTH = 0x20
    PROCESS_ERROR = 0x40


_BUSY = int(StatusFlag.BUSY)  # plain ints on the 500 Hz path: IntFlag arithmetic is slow
_INVALID_SIGNAL = int(StatusFlag.INVALID_SIGNAL)


def acquisition_time_ns(sig_count_val: int, acq_config: int = 0x08, *, bias: bool = False,
                        ref_count_val: int = DEFAULT_REF_COUNT, signal_counts: int | None = None) -> int:
    """Modelled acquisition time (module docstring).

    Args:
        sig_count_val: SIG_COUNT_VAL, the maximum signal acquisition count (0-255).
        acq_config: ACQ_CONFIG_REG; bit 2 selects `ref_count_val` instead of the default 5.
        bias: ACQ_COMMAND 0x04 (receiver bias correction) rather than 0x03.
        ref_count_val: REF_COUNT_VAL, used only when ACQ_CONFIG bit 2 is set.
        signal_counts: the counts actually integrated (a strong echo stops early); None = all.
    """
    n_max = max(1, int(sig_count_val))
    n_sig = n_max if signal_counts is None else max(1, min(n_max, int(signal_counts)))
    n_ref = max(1, int(ref_count_val)) if acq_config & 0x04 else DEFAULT_REF_COUNT
    return T_ACQ_FIXED_NS + (n_sig + n_ref) * T_ACQ_PER_COUNT_NS + (T_BIAS_CORRECTION_NS if bias else 0)


def max_range_m(sig_count_val: int) -> float:
    """Modelled maximum range for a 70 % reflective target: 40 m at the default count, ~n^(1/4)."""
    return RANGE_AT_DEFAULT_COUNT_M * (max(1, int(sig_count_val)) / DEFAULT_SIG_COUNT) ** 0.25


def _check_byte(name: str, value: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 0xFF:
        raise ValueError(f"{name} must be a byte 0x00-0xff, got {value!r}")


@dataclass(frozen=True)
class Preset:
    """The three registers that set the speed / range / sensitivity trade-off.

    Attributes:
        name: a short name (the CLI/TOML spelling).
        sig_count_val: SIG_COUNT_VAL 0x02, maximum acquisition count (rate ~ 1/n, range ~ n^(1/4)).
        acq_config: ACQ_CONFIG_REG 0x04 (bit 3 set = quick termination disabled, the default).
        threshold_bypass: THRESHOLD_BYPASS 0x1c (0 = the default peak/noise detection algorithm).
    """

    name: str
    sig_count_val: int
    acq_config: int
    threshold_bypass: int

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ValueError(f"preset name must be a non-empty string, got {self.name!r}")
        _check_byte("SIG_COUNT_VAL", self.sig_count_val)
        if self.sig_count_val == 0:
            raise ValueError("SIG_COUNT_VAL must be >= 1 (it is the number of acquisitions), got 0")
        _check_byte("ACQ_CONFIG_REG", self.acq_config)
        _check_byte("THRESHOLD_BYPASS", self.threshold_bypass)

    @property
    def registers(self) -> tuple[tuple[int, int], ...]:
        """(register, value) pairs in the order they are written."""
        return ((_REG_SIG_COUNT_VAL, self.sig_count_val), (_REG_ACQ_CONFIG_REG, self.acq_config),
                (_REG_THRESHOLD_BYPASS, self.threshold_bypass))

    def worst_acquisition_ns(self, bias: bool = True) -> int:
        """Modelled acquisition time with no return (all counts), with bias correction by default."""
        return acquisition_time_ns(self.sig_count_val, self.acq_config, bias=bias)

    @property
    def max_range_m(self) -> float:
        return max_range_m(self.sig_count_val)


# Garmin LIDARLite_Arduino_Library `LIDARLite::configure(0..5)` (the values Adafruit copies too).
PRESET_DEFAULT = Preset("default", 0x80, 0x08, 0x00)  # balanced; the power-on values
PRESET_SHORT_RANGE_HIGH_SPEED = Preset("short-range-high-speed", 0x1D, 0x08, 0x00)
PRESET_DEFAULT_RANGE_HIGHER_SPEED = Preset("default-range-higher-speed", 0x80, 0x00, 0x00)  # quick termination on
PRESET_MAX_RANGE = Preset("max-range", 0xFF, 0x08, 0x00)
PRESET_HIGH_SENSITIVITY = Preset("high-sensitivity", 0x80, 0x08, 0x80)  # more false returns
PRESET_LOW_SENSITIVITY = Preset("low-sensitivity", 0x80, 0x08, 0xB0)  # fewer false returns
PRESET_FAST_500HZ = Preset("fast-500hz", 0x14, 0x08, 0x00)
"""Ours, for the paper's 500 Hz (Table 1). At 400 kHz a cycle spends ~0.37 ms on the bus (trigger
68 us, distance read 113 us, the last status poll 90 us plus up to one 100 us poll interval of
overshoot) and 0.27 ms more on the register read-back once per 1000 readings (never on a
bias-corrected one), leaving ~1.5 ms of the 2 ms for the acquisition. Acquisition time scales with
SIG_COUNT_VAL (the manual's rate = 1/n), so the count is chosen to fit with margin: 20 (0x14) gives
1.23 ms, 1.43 ms with bias correction (worst case: no return integrates every count), so modelled
cycles are at most ~1.8 ms (bias) / ~1.9 ms (read-back). Garmin's 0x1d would take 1.61 ms with bias
correction, ~1.9 ms a cycle: too tight once a real kernel adds its per-transfer overhead. Range
scales as n^(1/4): ~25 m modelled, enough for the pile from 12 m altitude out to ~60 deg of sweep.
ACQ_CONFIG stays 0x08: quick termination would only shorten strong returns (not the worst case)
and costs accuracy. THRESHOLD_BYPASS stays 0 (the default detection algorithm). On a Pi,
per-transfer syscall overhead (~0.1 ms) eats into the margin: measure, and drop the count if
cycles overrun."""

PRESETS: dict[str, Preset] = {p.name: p for p in (
    PRESET_DEFAULT, PRESET_SHORT_RANGE_HIGH_SPEED, PRESET_DEFAULT_RANGE_HIGHER_SPEED, PRESET_MAX_RANGE,
    PRESET_HIGH_SENSITIVITY, PRESET_LOW_SENSITIVITY, PRESET_FAST_500HZ)}


def preset_by_name(name: str) -> Preset:
    try:
        return PRESETS[name]
    except KeyError:
        raise ValueError(f"unknown LIDAR-Lite preset {name!r}; known: {', '.join(PRESETS)}") from None


def _positive_int(name: str, value: int | None, allow_none: bool = False) -> None:
    if value is None and allow_none:
        return
    if isinstance(value, bool) or not isinstance(value, int) or value < 1:
        raise ValueError(f"{name} must be an integer >= 1{' or None' if allow_none else ''}, got {value!r}")


@dataclass(frozen=True)
class LidarLiteConfig:
    """Driver settings.

    Attributes:
        address: 7-bit I2C address (0x62 unless re-addressed).
        preset: the register preset applied at start-up, after a reset and after a glitch.
        bias_every: one measurement in this many uses receiver bias correction (the first one too).
        poll_interval_ns: STATUS polls are spaced this far apart on a grid from the trigger.
        busy_timeout_ns: give up on busy this long after the trigger; None = twice the preset's
            worst-case modelled acquisition + 1 ms.
        reset_after_failures: reset the part after this many consecutive readings that are 0 cm
            (PX4's known stuck state), TIMEOUT or BUS_ERROR (PX4 ll40ls uses 20); doubled after each
            reset that did not help (up to MAX_RESET_BACKOFF times), back to this after a good reading.
        reset_after_no_valid: also reset after this many consecutive readings without a range of
            any kind, 1 cm no-returns included; None = never (the default). A no-return is what a
            working part answers whenever nothing is in range: a drone standing on the floor before
            take-off, a lens cover, a sweep past far walls. With 1000 (2 s at 500 Hz) as the old
            default a fault-free networked flight reset a healthy part five times on the ground,
            25 ms of readings lost and a warning each time; a part that has really lost its
            settings is caught by the register read-back instead.
        reset_wait_ns: wait after the reset command before re-applying the preset (manual: ~22 ms).
        readback_every: read the preset registers back every this many readings; None = never.
        max_range_m: a distance above this cannot be real (the part reaches ~40 m): BUS_ERROR.
    """

    address: int = DEFAULT_ADDRESS
    preset: Preset = PRESET_DEFAULT
    bias_every: int = 100
    poll_interval_ns: int = 100_000
    busy_timeout_ns: int | None = None
    reset_after_failures: int = 20
    reset_after_no_valid: int | None = None
    reset_wait_ns: int = 25_000_000
    readback_every: int | None = 1000
    max_range_m: float = 60.0

    def __post_init__(self) -> None:
        if isinstance(self.address, bool) or not isinstance(self.address, int) or not 0x08 <= self.address <= 0x77:
            raise ValueError(f"I2C address must be a 7-bit address 0x08-0x77, got {self.address!r}")
        if not isinstance(self.preset, Preset):
            raise ValueError(f"preset must be a Preset (see PRESETS), got {self.preset!r}")
        _positive_int("bias_every", self.bias_every)
        _positive_int("poll_interval_ns", self.poll_interval_ns)
        _positive_int("busy_timeout_ns", self.busy_timeout_ns, allow_none=True)
        _positive_int("reset_after_failures", self.reset_after_failures)
        _positive_int("reset_after_no_valid", self.reset_after_no_valid, allow_none=True)
        if isinstance(self.reset_wait_ns, bool) or not isinstance(self.reset_wait_ns, int) or self.reset_wait_ns < 0:
            raise ValueError(f"reset_wait_ns must be an integer >= 0, got {self.reset_wait_ns!r}")
        _positive_int("readback_every", self.readback_every, allow_none=True)
        if not (math.isfinite(self.max_range_m) and self.max_range_m > 0.02):
            raise ValueError(f"max_range_m must be finite and > 0.02 m, got {self.max_range_m!r}")

    @property
    def timeout_ns(self) -> int:
        """The busy deadline actually used, measured from the trigger."""
        if self.busy_timeout_ns is not None:
            return self.busy_timeout_ns
        return 2 * self.preset.worst_acquisition_ns(bias=True) + 1_000_000


def busy_deadline_ns(preset: Preset, rate_hz: float, poll_interval_ns: int = 100_000) -> int:
    """A busy deadline that lets a loop at rate_hz keep its rate when the part sticks busy.

    Four fifths of the loop period (the rest is the trigger, the reads and the loop's own work),
    but never less than the preset's worst acquisition with bias correction plus one poll, so a
    healthy part is never cut off. A preset whose worst acquisition does not fit in the period at
    all cannot sustain the rate: ValueError, naming the rate that would work.
    """
    if not (math.isfinite(rate_hz) and rate_hz > 0):
        raise ValueError(f"sample rate must be > 0 Hz, got {rate_hz!r}")
    period = round(1e9 / rate_hz)
    worst = preset.worst_acquisition_ns(bias=True)
    if worst + poll_interval_ns >= period:
        raise ValueError(f"LIDAR-Lite preset {preset.name!r} takes up to {worst / 1e6:.2f} ms a reading; "
                         f"{rate_hz:g} Hz leaves {period / 1e6:.2f} ms: use a rate up to "
                         f"{math.floor(1e9 / (worst + poll_interval_ns) * 0.8)} Hz or a faster preset")
    return max(worst + poll_interval_ns, round(0.8 * period))


_REG_BYTES = [bytes((r,)) for r in range(256)]  # register-address writes without a fresh bytes() each time
_TRIGGER = bytes((_REG_ACQ_COMMAND, _CMD_MEASURE))  # the two acquisition commands, built once
_TRIGGER_BIAS = bytes((_REG_ACQ_COMMAND, _CMD_MEASURE_BIAS))

MAX_RESET_BACKOFF = 32
"""A stuck part is reset after 20, 40, 80 ... failures, at most 32 x 20 (about 1.3 s at 500 Hz)."""


@dataclass(frozen=True, slots=True)
class LidarLiteCounters:
    """The driver's counts since it was made: a snapshot (`LidarLite.counters()`), never a live dict.

    ok + no_return + timeouts + bus_errors + resetting is the number of readings; implausible is the
    part of bus_errors whose bytes could not be a distance; config_errors counts failed transfers
    while resetting, configuring or reading back; bias counts bias-corrected triggers.
    """

    ok: int = 0
    no_return: int = 0
    timeouts: int = 0
    bus_errors: int = 0
    resetting: int = 0
    implausible: int = 0
    resets: int = 0
    reconfigs: int = 0
    config_errors: int = 0
    bias: int = 0

    @property
    def readings(self) -> int:
        """Readings handed out, whatever their status."""
        return self.ok + self.no_return + self.timeouts + self.bus_errors + self.resetting

    @property
    def sensor_errors(self) -> int:
        """Failed transfers and busy timeouts: what the health report calls sensor errors."""
        return self.bus_errors + self.timeouts + self.config_errors

    def as_dict(self) -> dict[str, int]:
        """The counts by name (logs, JSON), in field order."""
        return {name: getattr(self, name) for name in COUNTER_NAMES}


COUNTER_NAMES = tuple(f.name for f in fields(LidarLiteCounters))
"""The counters' names, in order (`LidarLiteCounters`)."""

_STATUS_COUNTER = {ReadStatus.OK: "ok", ReadStatus.NO_RETURN: "no_return", ReadStatus.TIMEOUT: "timeouts",
                   ReadStatus.BUS_ERROR: "bus_errors", ReadStatus.RESETTING: "resetting"}


@dataclass
class _Pending:
    t_ns: int
    bias: bool
    error: I2CError | None = None
    resetting: bool = False


class LidarLite:
    """The LIDAR-Lite v3 on an I2CBus.

    Args:
        bus: the I2C bus (smbus2 on the drone, the SITL's simulated bus in lockstep).
        clock: the payload clock; the driver sleeps on it between polls and stamps readings with it.
        config: address, preset, schedules and limits.
        configure: write the preset now (raises I2CError if the part does not answer).
    """

    def __init__(self, bus: I2CBus, clock: Clock, config: LidarLiteConfig | None = None, *,
                 configure: bool = True) -> None:
        self.bus = bus
        self.clock = clock
        self.config = config or LidarLiteConfig()
        self._counts: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)  # mutable here, snapshots out
        self.last_error: I2CError | None = None
        self._preset = self.config.preset
        self._bias_countdown = 0
        self._pending: _Pending | None = None
        self._failure_run = 0
        self._no_valid_run = 0
        self._since_readback = 0
        self._reset_after = self.config.reset_after_failures  # grows while resets do not help
        self._reloaded_at_ns: int | None = None  # an automatic reset is under way until then
        self._done_after_ns: dict[bool, int | None] = {False: None, True: None}  # learned busy time
        self._shortest_ns = acquisition_time_ns(self._preset.sig_count_val, self._preset.acq_config, signal_counts=1)
        self._worst_ns = {b: self._preset.worst_acquisition_ns(bias=b) for b in (False, True)}
        if configure:
            self.configure()

    def counters(self) -> LidarLiteCounters:
        """What the driver has counted so far (a frozen snapshot: later readings do not change it)."""
        return LidarLiteCounters(**self._counts)

    # -- register access: split transfers only ------------------------------------------------

    def _write_reg(self, reg: int, value: int) -> None:
        self.bus.write(self.config.address, bytes((reg, value)))

    def _read_regs(self, reg: int, n: int) -> bytes:
        """Write the register address (STOP), then read n bytes in a separate transfer."""
        self.bus.write(self.config.address, _REG_BYTES[reg])
        data = bytes(self.bus.read(self.config.address, n))
        if len(data) != n:
            raise I2CError(f"short read at 0x{self.config.address:02x} register 0x{reg:02x}: "
                           f"{len(data)} of {n} bytes")
        return data

    # -- configuration ---------------------------------------------------------------------------

    @property
    def preset(self) -> Preset:
        return self._preset

    def configure(self, preset: Preset | None = None) -> None:
        """Write a preset (default: the configured one) and keep it for resets and read-backs.

        Raises:
            I2CError: a write failed (the preset is still remembered, a read-back will retry).
        """
        if preset is not None:
            if not isinstance(preset, Preset):
                raise ValueError(f"preset must be a Preset (see PRESETS), got {preset!r}")
            self._preset = preset
        self._done_after_ns = {False: None, True: None}  # a new preset has its own timing
        p = self._preset
        self._shortest_ns = acquisition_time_ns(p.sig_count_val, p.acq_config, signal_counts=1)
        self._worst_ns = {b: p.worst_acquisition_ns(bias=b) for b in (False, True)}
        for reg, value in self._preset.registers:
            self._write_reg(reg, value)

    def verify_configuration(self) -> bool:
        """Read the preset registers back; re-apply the preset if they differ (a power glitch
        resets them to the power-on values). True if they matched."""
        try:
            actual = [(reg, self._read_regs(reg, 1)[0]) for reg, _ in self._preset.registers]
        except I2CError as exc:
            self._config_error("register read-back", exc)
            return False
        if actual == list(self._preset.registers):
            return True
        self._counts["reconfigs"] += 1
        log.warning("LIDAR-Lite registers %s differ from preset %s: re-applying it",
                    ", ".join(f"0x{r:02x}=0x{v:02x}" for r, v in actual), self._preset.name)
        try:
            self.configure()
        except I2CError as exc:
            self._config_error("re-applying the preset", exc)
        self._bias_countdown = 0  # a glitch lost the receiver bias state too
        return False

    def reset(self) -> bool:
        """Reset the part (ACQ_COMMAND 0x00), wait for it to reload, re-apply the preset.

        Returns False (and counts config_errors) if a transfer failed; the next read-back retries.
        """
        if self._pending is not None:
            raise RuntimeError("reset() during a measurement: call measure_finish() first")
        errors = self._counts["config_errors"]
        self._start_reset("asked for")  # this one waits: it supersedes an automatic reset under way
        self.clock.sleep_until_ns(self._reloaded_at_ns)
        self._finish_reset()
        return self._counts["config_errors"] == errors

    def _start_reset(self, reason: str) -> None:
        """The automatic reset, without blocking: the reset command now, the preset once the part
        has reloaded (`measure_start` after reset_wait_ns). Meanwhile readings come back RESETTING at
        the loop's rate, so a payload keeps its tick grid (servo pulses, pose pumping, health).
        `reason` says why, in the operator's warning."""
        self._counts["resets"] += 1
        log.warning("resetting the LIDAR-Lite at 0x%02x: %s", self.config.address, reason)
        try:
            self._write_reg(_REG_ACQ_COMMAND, _CMD_RESET)
        except I2CError as exc:
            self._config_error("reset command", exc)
        self._reloaded_at_ns = self.clock.now_ns() + self.config.reset_wait_ns
        self._bias_countdown = 0
        self._failure_run = self._no_valid_run = 0

    def _finish_reset(self) -> None:
        self._reloaded_at_ns = None
        try:
            self.configure()
        except I2CError as exc:
            self._config_error("configuring after reset", exc)

    def _config_error(self, what: str, exc: I2CError) -> None:
        self._counts["config_errors"] += 1
        self.last_error = exc
        log.warning("LIDAR-Lite %s failed: %s", what, exc)

    # -- measuring ---------------------------------------------------------------------------------

    @property
    def measuring(self) -> bool:
        """True between measure_start() and measure_finish()."""
        return self._pending is not None

    def read(self) -> Reading:
        """Trigger, wait and collect one reading (measure_start + measure_finish)."""
        self.measure_start()
        return self.measure_finish()

    def measure_start(self) -> int:
        """Trigger an acquisition and return its trigger time (ns on the driver's clock) at once.

        Never raises on a bus error: a failed trigger is reported by measure_finish() as BUS_ERROR.
        """
        if self._pending is not None:
            raise RuntimeError("measure_start() called twice without measure_finish()")
        if self._reloaded_at_ns is not None:
            now = self.clock.now_ns()
            if now < self._reloaded_at_ns:
                self._pending = _Pending(now, False, resetting=True)
                return now
            self._finish_reset()
        bias = self._bias_countdown <= 0
        try:
            self.bus.write(self.config.address, _TRIGGER_BIAS if bias else _TRIGGER)
        except I2CError as exc:
            t_ns = self.clock.now_ns()
            self._pending = _Pending(t_ns, bias, exc)
            return t_ns
        t_ns = self.clock.now_ns()  # just after the STOP that started the acquisition
        if bias:
            self._bias_countdown = self.config.bias_every - 1
            self._counts["bias"] += 1
        else:
            self._bias_countdown -= 1
        self._pending = _Pending(t_ns, bias)
        return t_ns

    def measure_finish(self) -> Reading:
        """Wait for the triggered acquisition (busy poll with a deadline) and read its range."""
        pending = self._pending
        if pending is None:
            raise RuntimeError("measure_finish() without measure_start()")
        self._pending = None
        if pending.resetting:
            self._counts["resetting"] += 1
            return Reading(None, ReadStatus.RESETTING, pending.t_ns, 0)
        if pending.error is not None:
            self.last_error = pending.error
            reading, raw_cm = Reading(None, ReadStatus.BUS_ERROR, pending.t_ns, 0), None
        else:
            reading, raw_cm = self._collect(pending.t_ns, pending.bias)
        self._account(reading, raw_cm)
        self._since_readback += 1
        every = self.config.readback_every
        # Never on a bias-corrected reading: that cycle has no time to spare at 500 Hz.
        if every is not None and self._since_readback >= every and not pending.bias:
            self._since_readback = 0
            self.verify_configuration()
        return reading

    def _collect(self, t_ns: int, bias: bool) -> tuple[Reading, int | None]:
        cfg = self.config
        deadline = t_ns + cfg.timeout_ns
        polls = 0
        # No acquisition can end before the shortest the part makes (one signal count), and most
        # take about as long as the last one (same preset, similar range): the first poll goes one
        # poll interval before the last observed completion, never before that minimum. Typically
        # two polls (busy, done) instead of five on a 0.1 ms grid: less bus traffic, less CPU.
        learned = self._done_after_ns[bias]
        next_poll = t_ns + max(self._shortest_ns, (learned or 0) - cfg.poll_interval_ns)
        self.clock.sleep_until_ns(next_poll)
        while True:
            polls += 1
            try:
                status = self._read_regs(_REG_STATUS, 1)[0]
            except I2CError as exc:
                return self._bus_error(exc, t_ns, polls), None
            if not status & _BUSY:
                break
            now = self.clock.now_ns()
            if now >= deadline:
                log.debug("LIDAR-Lite busy for %d ns after the trigger: timeout", now - t_ns)
                return Reading(None, ReadStatus.TIMEOUT, t_ns, polls), None
            next_poll += cfg.poll_interval_ns
            if next_poll > now:
                self.clock.sleep_until_ns(min(next_poll, deadline))
            else:
                next_poll = now  # behind the grid (slow bus): poll again at once
        # An upper bound of this acquisition; capped at the preset's modelled worst case so one
        # late poll (a descheduled process) cannot push the following first polls late.
        self._done_after_ns[bias] = min(self.clock.now_ns() - t_ns, self._worst_ns[bias])
        try:
            hi, lo = self._read_regs(_REG_DISTANCE, 2)
        except I2CError as exc:
            return self._bus_error(exc, t_ns, polls), None
        cm = hi << 8 | lo
        if cm <= 1 or status & _INVALID_SIGNAL:
            return Reading(None, ReadStatus.NO_RETURN, t_ns, polls), cm
        if cm > cfg.max_range_m * 100.0:
            self._counts["implausible"] += 1
            self.last_error = I2CError(f"implausible distance {cm} cm (bytes 0x{hi:02x} 0x{lo:02x}) "
                                       f"from 0x{cfg.address:02x}")
            log.debug("%s", self.last_error)
            return Reading(None, ReadStatus.BUS_ERROR, t_ns, polls), cm
        return Reading(cm / 100.0, ReadStatus.OK, t_ns, polls), cm

    def _bus_error(self, exc: I2CError, t_ns: int, polls: int) -> Reading:
        self.last_error = exc
        log.debug("LIDAR-Lite transfer failed: %s", exc)
        return Reading(None, ReadStatus.BUS_ERROR, t_ns, polls)

    def _account(self, reading: Reading, raw_cm: int | None) -> None:
        self._counts[_STATUS_COUNTER[reading.status]] += 1
        if reading.status == ReadStatus.OK:
            self._failure_run = self._no_valid_run = 0
            self._reset_after = self.config.reset_after_failures
            return
        self._no_valid_run += 1
        zero = reading.status == ReadStatus.NO_RETURN and raw_cm == 0
        if reading.status == ReadStatus.NO_RETURN and not zero:
            self._failure_run = 0  # a sane "nothing there" shows the part is alive
        else:
            self._failure_run += 1
        cfg = self.config
        if self._failure_run >= self._reset_after:
            reason = (f"{self._failure_run} readings in a row failed (last: "
                      f"{'0 cm' if zero else reading.status.name})")
            # A reset that did not help is not repeated as often: each costs ~25 ms of no readings,
            # and a part that stays stuck would otherwise spend much of the loop's time resetting.
            self._reset_after = min(2 * self._reset_after, MAX_RESET_BACKOFF * cfg.reset_after_failures)
            self._start_reset(reason)
        elif cfg.reset_after_no_valid is not None and self._no_valid_run >= cfg.reset_after_no_valid:
            self._start_reset(f"{self._no_valid_run} readings in a row without a range")
