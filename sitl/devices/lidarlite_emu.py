"""An emulated Garmin LIDAR-Lite v3: its register file on the simulated I2C bus, so the payload's
unchanged driver (or anyone else's, e.g. Adafruit's) measures the simulated world.

What is modelled (LIDAR-Lite v3 Operation Manual, and the lore in firmware_py.drivers.lidarlite):

- Registers with their power-on values: SIG_COUNT_VAL 0x02 = 0x80, ACQ_CONFIG_REG 0x04 = 0x08,
  OUTER_LOOP_COUNT 0x11 = 0x01, REF_COUNT_VAL 0x12 = 0x05, THRESHOLD_BYPASS 0x1c = 0x00,
  I2C_CONFIG 0x1e = 0x00, MEASURE_DELAY 0x45 = 0x14, POWER_CONTROL 0x65 = 0x80, STATUS 0x01 with the
  health bit set, UNIT_ID 0x16/0x17 from the constructor. A write sets the register pointer (bit 7
  of the address byte = auto-increment) and stores any data bytes into writable registers; a read
  clocks out bytes from the pointer (the same register again and again without auto-increment).
- ACQ_COMMAND 0x00: 0x03 / 0x04 start an acquisition (0x04 with receiver bias correction); 0x00
  resets: busy for 22 ms, then every register reloads its power-on value (writes made meanwhile
  are lost, as the FPGA reloads).
- An acquisition sets STATUS busy (bit 0) until it ends. Its duration is
  `firmware_py.drivers.lidarlite.acquisition_time_ns` (700 us + 21 us per signal and reference
  count + 200 us for bias correction; fitted to the manual's 270 Hz typical / 650 Hz fast /
  >1000 Hz short-range update rates and its "rate = 1/n"). No return integrates all SIG_COUNT_VAL
  counts; a return stops once the correlation peak would saturate, modelled as
  ceil(2 counts/m^2 * r^2) counts (inverse-square signal; 8 m uses the default 128), a quarter of
  that with quick termination enabled (ACQ_CONFIG bit 3 clear). That saturation constant is an
  assumption, not a datasheet figure.
- The range is sampled from `range_at(t_ns)` at the acquisition START, the instant the driver stamps
  (`Reading.t_ns`), so SITL samples pair with the true pose exactly. (The real part integrates over
  the acquisition; its centroid is ~half an acquisition later: see the driver's docstring.)
- No return (range_at gives None or non-finite, or the range exceeds 40 m * (n/128)^(1/4) for the
  current SIG_COUNT_VAL n, the manual's range law) reads 1 cm with STATUS bit 3 (invalid signal).
  Otherwise FULL_DELAY 0x0f/0x10 hold the range in cm (rounded to 1 cm) after optional Gaussian noise
  (sigma 2.5 cm in the paper's Appendix A; off by default); LAST_DELAY 0x14/0x15 the previous one,
  VELOCITY 0x09 their difference. Until an acquisition ends the distance registers keep the previous
  result (Garmin's ShortRangeHighSpeed example reads it while the next one runs).
- A combined transfer (repeated START) is not understood: the part never latched the register
  address, and the read returns 0xff bytes (a Pi kernel in combined mode reads 255s from it).
- THRESHOLD_BYPASS, OUTER_LOOP_COUNT (burst mode) and MEASURE_DELAY are stored but not modelled.

Fault knobs: `stuck_busy` (busy never clears while set), `power_glitch()` (registers back to their
power-on values at once, the acquisition in flight lost), `garbage_reads` (probability that a read
returns random bytes).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import NamedTuple

import numpy as np

from firmware_py.drivers.lidarlite import RESET_TIME_NS, StatusFlag, acquisition_time_ns, max_range_m
from firmware_py.hal import Clock
from sitl.sensing.noise import RangeNoise

ADDRESS = 0x62


# The part's register map (manual), kept apart from the driver's on purpose: an independent model
# catches a driver that writes the wrong register.
ACQ_COMMAND = 0x00
STATUS = 0x01
SIG_COUNT_VAL = 0x02
ACQ_CONFIG_REG = 0x04
VELOCITY = 0x09
PEAK_CORR = 0x0C
NOISE_PEAK = 0x0D
SIGNAL_STRENGTH = 0x0E
FULL_DELAY_HIGH = 0x0F
FULL_DELAY_LOW = 0x10
OUTER_LOOP_COUNT = 0x11
REF_COUNT_VAL = 0x12
LAST_DELAY_HIGH = 0x14
LAST_DELAY_LOW = 0x15
UNIT_ID_HIGH = 0x16
UNIT_ID_LOW = 0x17
I2C_ID_HIGH = 0x18
I2C_ID_LOW = 0x19
I2C_SEC_ADDR = 0x1A
THRESHOLD_BYPASS = 0x1C
I2C_CONFIG = 0x1E
COMMAND = 0x40
MEASURE_DELAY = 0x45
ACQ_SETTINGS = 0x5D
POWER_CONTROL = 0x65
AUTO_INCREMENT = 0x80
_BUSY, _HEALTH, _INVALID_SIGNAL = int(StatusFlag.BUSY), int(StatusFlag.HEALTH), int(StatusFlag.INVALID_SIGNAL)

_BYTE = [bytes((v,)) for v in range(256)]

POWER_ON: dict[int, int] = {
    STATUS: int(StatusFlag.HEALTH), SIG_COUNT_VAL: 0x80, ACQ_CONFIG_REG: 0x08, OUTER_LOOP_COUNT: 0x01,
    REF_COUNT_VAL: 0x05, THRESHOLD_BYPASS: 0x00, I2C_CONFIG: 0x00, MEASURE_DELAY: 0x14, POWER_CONTROL: 0x80,
}
WRITABLE = frozenset({SIG_COUNT_VAL, ACQ_CONFIG_REG, OUTER_LOOP_COUNT, REF_COUNT_VAL, I2C_ID_HIGH, I2C_ID_LOW,
                      I2C_SEC_ADDR, THRESHOLD_BYPASS, I2C_CONFIG, COMMAND, MEASURE_DELAY, ACQ_SETTINGS,
                      POWER_CONTROL})

SATURATION_COUNTS_PER_M2 = 2.0
"""Counts after which a return's correlation peak saturates, per m^2 of range (an assumption)."""
QUICK_TERMINATION_FACTOR = 4
"""Quick termination stops at this fraction of the saturating count (an assumption)."""


class Acquisition(NamedTuple):
    """What the emulated part measured, for tests and SITL diagnostics (a NamedTuple: one is built
    per acquisition, 500 a second, and a frozen dataclass costs ~1 us more to build).

    Attributes:
        t_start_ns: when the acquisition started (the trigger's STOP), where range_at was sampled.
        t_done_ns: when busy clears (unless stuck).
        true_range_m: range_at(t_start_ns) as given (None: no target).
        distance_cm: what the distance registers will hold (1 = no return).
        status: STATUS bits after the acquisition (busy clear).
        counts: signal acquisitions integrated.
        bias: receiver bias correction was requested (ACQ_COMMAND 0x04).
    """

    t_start_ns: int
    t_done_ns: int
    true_range_m: float | None
    distance_cm: int
    status: int
    counts: int
    bias: bool


class EmulatedLidarLite:
    """A LIDAR-Lite v3 register file, attached to a SimI2CBus (`bus.attach(0x62, lidar)`).

    Args:
        clock: the simulated clock (the bus advances it; the part reads it to time acquisitions).
        range_at: true range in metres along the beam at a time in ns, or None for no target (the
            SITL ray-casts the true pose and servo angle at that time).
        range_noise_sigma_m: Gaussian range noise before the 1 cm quantisation; 0 = none (the
            paper's Appendix A uses 0.025 m).
        range_noise: a sensor-noise model (`sitl.sensing.noise.RangeNoiser`): what the part reports for
            the true range, None for a no-return (datasheet dropouts); applied before the 1 cm quantisation.
        rng: generator for noise and garbage reads (default: seeded 0, so runs repeat).
        unit_id: the 16-bit serial number in UNIT_ID_HIGH/LOW.
        model_range_limit: no return beyond the n^(1/4) range law for the current SIG_COUNT_VAL.
        stuck_busy, garbage_reads: fault knobs (see the module docstring); attributes, settable.
    """

    def __init__(self, clock: Clock, range_at: Callable[[int], float | None], *, range_noise_sigma_m: float = 0.0,
                 rng: np.random.Generator | None = None, unit_id: int = 0x5A17, model_range_limit: bool = True,
                 stuck_busy: bool = False, garbage_reads: float = 0.0, range_noise: RangeNoise | None = None) -> None:
        if not callable(range_at):
            raise ValueError(f"range_at must be a callable t_ns -> range in m or None, got {range_at!r}")
        if not (math.isfinite(range_noise_sigma_m) and range_noise_sigma_m >= 0.0):
            raise ValueError(f"range noise sigma must be finite and >= 0 m, got {range_noise_sigma_m!r}")
        if isinstance(unit_id, bool) or not isinstance(unit_id, int) or not 0 <= unit_id <= 0xFFFF:
            raise ValueError(f"unit id must be a 16-bit integer, got {unit_id!r}")
        self.clock = clock
        self.range_at = range_at
        self.range_noise_sigma_m = float(range_noise_sigma_m)
        self.range_noise = range_noise
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.unit_id = unit_id
        self.model_range_limit = model_range_limit
        self.stuck_busy = stuck_busy
        self.garbage_reads = garbage_reads
        self.counters: dict[str, int] = dict.fromkeys(
            ("acquisitions", "bias_acquisitions", "retriggers", "resets", "power_glitches", "combined_transfers",
             "garbage_reads", "ignored_writes"), 0)
        self.last_acquisition: Acquisition | None = None
        self.regs = bytearray(0x80)
        self._durations: dict[tuple[int, int, bool, int, int], int] = {}
        self._range_limits: dict[int, float] = {}
        self._pending: Acquisition | None = None
        self._reset_done_ns: int | None = None
        self._ptr = 0
        self._auto = False
        self._load_power_on()

    # -- knobs -------------------------------------------------------------------------------

    @property
    def garbage_reads(self) -> float:
        return self._garbage_reads

    @garbage_reads.setter
    def garbage_reads(self, p: float) -> None:
        if not (isinstance(p, int | float) and math.isfinite(p) and 0.0 <= p <= 1.0):
            raise ValueError(f"garbage read probability must be in [0, 1], got {p!r}")
        self._garbage_reads = float(p)

    def power_glitch(self) -> None:
        """A brown-out: every register back to its power-on value now, the acquisition in flight lost."""
        self.counters["power_glitches"] += 1
        self._load_power_on()

    def _load_power_on(self) -> None:
        self.regs[:] = bytes(len(self.regs))
        for reg, value in POWER_ON.items():
            self.regs[reg] = value
        self.regs[UNIT_ID_HIGH], self.regs[UNIT_ID_LOW] = self.unit_id >> 8, self.unit_id & 0xFF
        self._pending = None
        self._reset_done_ns = None
        self._ptr, self._auto = 0, False

    # -- state -------------------------------------------------------------------------------

    @property
    def busy(self) -> bool:
        """What STATUS bit 0 reads now."""
        self._advance()
        return self._busy()

    def _busy(self) -> bool:
        return self.stuck_busy or self._pending is not None or self._reset_done_ns is not None

    def _advance(self) -> None:
        """Finish whatever has finished by now (lazily, at each bus access)."""
        if self._reset_done_ns is None and self._pending is None:
            return  # idle: nothing can finish
        now = self.clock.now_ns()
        if self._reset_done_ns is not None and now >= self._reset_done_ns:
            self._load_power_on()
        if self._pending is not None and not self.stuck_busy and now >= self._pending.t_done_ns:
            self._complete(self._pending)

    def _complete(self, acq: Acquisition) -> None:
        prev = self.regs[FULL_DELAY_HIGH] << 8 | self.regs[FULL_DELAY_LOW]
        cm = acq.distance_cm
        self.regs[LAST_DELAY_HIGH], self.regs[LAST_DELAY_LOW] = prev >> 8, prev & 0xFF
        self.regs[FULL_DELAY_HIGH], self.regs[FULL_DELAY_LOW] = cm >> 8, cm & 0xFF
        self.regs[VELOCITY] = max(-128, min(127, cm - prev)) & 0xFF
        r = acq.true_range_m
        if acq.status & _INVALID_SIGNAL or r is None:
            self.regs[SIGNAL_STRENGTH] = self.regs[PEAK_CORR] = 0
        else:  # rough inverse-square strength; a saturated peak when integration stopped early
            self.regs[SIGNAL_STRENGTH] = max(16, min(255, round(255 * (4.0 / max(r, 4.0)) ** 2)))
            self.regs[PEAK_CORR] = 0xFF if acq.counts < max(1, self.regs[SIG_COUNT_VAL]) else 0xA0
        self.regs[NOISE_PEAK] = 0x20
        self.regs[STATUS] = acq.status
        self._pending = None

    # -- acquisitions --------------------------------------------------------------------------

    def _start_acquisition(self, bias: bool) -> None:
        t0 = self.clock.now_ns()
        if self._pending is not None:
            self.counters["retriggers"] += 1  # the new command restarts the acquisition
        n_max = max(1, self.regs[SIG_COUNT_VAL])
        acq_config = self.regs[ACQ_CONFIG_REG]
        raw = self.range_at(t0)
        true_r = None if raw is None else float(raw)
        limit_m = self._range_limits.get(n_max)
        if limit_m is None:
            limit_m = self._range_limits[n_max] = max_range_m(n_max)
        in_range = not self.model_range_limit or (true_r is not None and true_r <= limit_m)
        measured_r = true_r
        if self.range_noise is not None and true_r is not None and math.isfinite(true_r) and true_r > 0.0:
            measured_r = self.range_noise.measure(true_r)  # None: the noise model's no-return
        if measured_r is not None and true_r is not None and math.isfinite(true_r) and true_r > 0.0 and in_range:
            counts = math.ceil(SATURATION_COUNTS_PER_M2 * true_r * true_r)
            if not acq_config & 0x08:  # quick termination enabled
                counts = math.ceil(counts / QUICK_TERMINATION_FACTOR)
            counts = max(1, min(n_max, counts))
            measured = measured_r
            if self.range_noise_sigma_m > 0.0:
                measured += float(self.rng.normal(0.0, self.range_noise_sigma_m))
            cm = max(0, min(0xFFFF, math.floor(measured * 100.0 + 0.5)))
            status = _HEALTH
        else:
            counts, cm = n_max, 1
            status = _HEALTH | _INVALID_SIGNAL
        key = (n_max, acq_config, bias, self.regs[REF_COUNT_VAL], counts)
        duration = self._durations.get(key)
        if duration is None:  # a handful of distinct settings per run: model each once
            duration = self._durations[key] = acquisition_time_ns(
                n_max, acq_config, bias=bias, ref_count_val=key[3], signal_counts=counts)
        acq = Acquisition(t0, t0 + duration, true_r, cm, status, counts, bias)
        self._pending = self.last_acquisition = acq
        self.counters["acquisitions"] += 1
        if bias:
            self.counters["bias_acquisitions"] += 1

    def _start_reset(self) -> None:
        self.counters["resets"] += 1
        self._pending = None
        self._reset_done_ns = self.clock.now_ns() + RESET_TIME_NS

    # -- the I2C device protocol ----------------------------------------------------------------

    def on_write(self, data: bytes) -> None:
        """A write transfer: [register address (bit 7 = auto-increment), data...]."""
        if self._pending is not None or self._reset_done_ns is not None:
            self._advance()
        if len(data) == 1:  # the register pointer only: what most transfers are
            b = data[0]
            self._ptr, self._auto = b & 0x7F, b >= AUTO_INCREMENT
            return
        if not data:
            return  # address-only probe
        self._ptr, self._auto = data[0] & 0x7F, bool(data[0] & AUTO_INCREMENT)
        values = data[1:]
        if self._reset_done_ns is not None:
            self.counters["ignored_writes"] += len(values)  # reloading: the write is lost
            return
        for i, value in enumerate(values):
            self._write_reg((self._ptr + i) & 0x7F if self._auto else self._ptr, value)

    def _write_reg(self, reg: int, value: int) -> None:
        if reg == ACQ_COMMAND:
            if value == 0x00:
                self._start_reset()
            elif value in (0x03, 0x04):
                self._start_acquisition(bias=value == 0x04)
            else:
                self.counters["ignored_writes"] += 1
        elif reg in WRITABLE:
            self.regs[reg] = value
        else:
            self.counters["ignored_writes"] += 1  # read-only or reserved

    def on_read(self, n: int) -> bytes:
        """A read transfer: n bytes from the register pointer."""
        if self._pending is not None or self._reset_done_ns is not None:
            self._advance()
        if self._garbage_reads > 0.0 and self.rng.random() < self._garbage_reads:
            self.counters["garbage_reads"] += 1
            return bytes(self.rng.integers(0, 256, size=n, dtype=np.uint8).tolist())
        ptr = self._ptr
        if n == 1:
            return _BYTE[self.regs[STATUS] | (_BUSY if self._busy() else 0) if ptr == STATUS else self.regs[ptr]]
        if self._auto and STATUS < ptr and ptr + n <= len(self.regs):  # a block past STATUS: plain bytes
            return bytes(self.regs[ptr:ptr + n])
        return bytes([self._read_reg((self._ptr + i) & 0x7F if self._auto else self._ptr) for i in range(n)])

    def _read_reg(self, reg: int) -> int:
        if reg == STATUS:
            return self.regs[STATUS] | (_BUSY if self._busy() else 0)
        return self.regs[reg]

    def on_write_read(self, data: bytes, n: int) -> bytes:
        """A combined transfer (repeated START): not supported by the part, reads the idle level."""
        self._advance()
        self.counters["combined_transfers"] += 1
        return b"\xff" * n
