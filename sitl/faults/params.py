"""SIM_PS_* parameters: fault injection changed while the SITL runs, ArduPilot's `SIM_*` style.

A ground station sets them with PARAM_SET like any parameter (MAVProxy: `param set SIM_PS_LOSS 10`)
and they act at once, as ArduPilot's SIM_* do: a setting (loss, latency, NACK rate ...) changes the
running injection, an action (outage, reboot, stuck busy, power glitch, stuck servo) starts now.
They are served beside the vehicle's own parameters by any `MavlinkVehicleServer` given a
`FaultParams` as `extra_params`; `pilescan-sitl serve` always has them (`sitl.devices.networked.NetworkedFaults`).

| name | unit, range | what it does | reads back |
|---|---|---|---|
| SIM_PS_LOSS | %, 0-100 | MAVLink packets lost, both directions | the setting |
| SIM_PS_DUP | %, 0-100 | packets sent twice | the setting |
| SIM_PS_REORDER | %, 0-100 | packets held back behind the next one | the setting |
| SIM_PS_LAT_MS | ms, 0-10000 | latency added to every packet | the setting |
| SIM_PS_JIT_MS | ms, 0-10000 | jitter added, uniform 0-J (the order is kept) | the setting |
| SIM_PS_OUTAGE | s, 0-3600 | both directions silent for S s from now (0 ends it) | seconds left |
| SIM_PS_REBOOT | s, 0-60 | the autopilot reboots now, silent for S s (0: nothing) | 0 |
| SIM_PS_I2C_NACK | %, 0-100 | I2C transfers NACKed | the setting |
| SIM_PS_BUSY | s, 0-3600 | the LiDAR's busy flag sticks for S s from now (0 frees it) | seconds left |
| SIM_PS_PWRGLT | 0 or 1 | 1: the LiDAR's power glitches now (registers to power-on values) | 0 |
| SIM_PS_GARBAGE | %, 0-100 | LiDAR register reads that return random bytes | the setting |
| SIM_PS_GLITCH | %, 0-100 | LiDAR readings replaced by 40 m or 1 cm | the setting |
| SIM_PS_SRV_STK | 0 or 1 | 1: the servo shaft stops where it is now; 0: it moves again | the state |
| SIM_PS_SRV_SLOW | factor, 0.05-1 | the servo slews at this fraction of its calibrated rate | the setting |
| SIM_PS_SRV_DLY | ms, 0-1000 | dead time before the servo acts on a pulse | the setting |

The link ones are listed when the server's transport is faulted, SIM_PS_REBOOT when the injector can
reboot the autopilot, the device ones when it has the emulated LiDAR and servo (`serve --devices`).
An out-of-range value is refused (the server says why in a STATUSTEXT and reads the old value back).
The settings mirror `FaultSpec` fields and start from the `--fault` values; the timed `--fault`
faults stay timed from the survey start, the actions here count from when they are set.

The PARAM_VALUE acknowledging a set carries the value set, actions included (MAVProxy re-sends a
`param set` until the value it sent comes back, and a re-sent reboot or glitch would act again);
"reads back" is what a later read gives. An outage starts just after that acknowledgement has gone
out, and a reboot after it too, so a ground station sees its request accepted before the link goes
quiet.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from sitl.faults.injector import GLITCH_RANGE_M, FaultInjector, FaultSpec, FaultyLink


@dataclass(frozen=True)
class SimParam:
    """One SIM_PS_* parameter."""

    name: str
    part: str
    """What the injector must have for the parameter to be listed: "link", "autopilot" or "devices"."""
    lo: float
    hi: float
    unit: str
    meaning: str
    field: str | None = None
    """The FaultSpec setting it mirrors; None for an action (see FaultParams)."""
    flag: bool = False
    """Only 0 or 1."""


PARAMS: tuple[SimParam, ...] = (
    SimParam("SIM_PS_LOSS", "link", 0, 100, "%", "MAVLink packets lost, both directions", "link_loss_pct"),
    SimParam("SIM_PS_DUP", "link", 0, 100, "%", "packets sent twice", "link_dup_pct"),
    SimParam("SIM_PS_REORDER", "link", 0, 100, "%", "packets held back behind the next one", "link_reorder_pct"),
    SimParam("SIM_PS_LAT_MS", "link", 0, 10_000, "ms", "latency added to every packet", "link_latency_ms"),
    SimParam("SIM_PS_JIT_MS", "link", 0, 10_000, "ms", "jitter added, uniform 0-J", "link_jitter_ms"),
    SimParam("SIM_PS_OUTAGE", "link", 0, 3600, "s", "both directions silent for S s from now"),
    SimParam("SIM_PS_REBOOT", "autopilot", 0, 60, "s", "the autopilot reboots now, silent for S s"),
    SimParam("SIM_PS_I2C_NACK", "devices", 0, 100, "%", "I2C transfers NACKed", "i2c_nack_pct"),
    SimParam("SIM_PS_BUSY", "devices", 0, 3600, "s", "the LiDAR's busy flag sticks for S s from now"),
    SimParam("SIM_PS_PWRGLT", "devices", 0, 1, "", "1: the LiDAR's power glitches now", flag=True),
    SimParam("SIM_PS_GARBAGE", "devices", 0, 100, "%", "LiDAR reads returning random bytes", "lidar_garbage_pct"),
    SimParam("SIM_PS_GLITCH", "devices", 0, 100, "%", "LiDAR readings replaced by 40 m or 1 cm", "lidar_glitch_pct"),
    SimParam("SIM_PS_SRV_STK", "devices", 0, 1, "", "1: the servo shaft is stuck; 0: free", flag=True),
    SimParam("SIM_PS_SRV_SLOW", "devices", 0.05, 1, "", "servo slew rate, fraction of calibrated",
             "servo_slow_factor"),
    SimParam("SIM_PS_SRV_DLY", "devices", 0, 1000, "ms", "servo dead time", "servo_delay_ms"),
)
BY_NAME = {p.name: p for p in PARAMS}


class LiveFaultyLink(FaultyLink):
    """A FaultyLink that can also be silenced on demand: `outage_ns` = (from, until), the link's own time."""

    def __init__(self, *args, **kwargs) -> None:
        super().__init__(*args, **kwargs)
        self.outage_ns: tuple[int, int] | None = None

    def _in_outage(self, t_ns: int) -> bool:
        w = self.outage_ns
        return (w is not None and w[0] <= t_ns < w[1]) or super()._in_outage(t_ns)


class LiveFaultInjector(FaultInjector):
    """A FaultInjector whose injection can change while it runs (what the SIM_PS_* parameters drive).

    `update(**settings)` changes FaultSpec settings at once; the `*_now` methods act at once, whether
    or not the survey has started. The FaultSpec's own timed faults stay timed from the survey start.
    """

    def __init__(self, spec: FaultSpec) -> None:
        super().__init__(spec)
        self.links: list[LiveFaultyLink] = []
        self.busy_until_ns: int | None = None  # stuck busy on demand, until then
        self._servo_cal0 = None  # the servo's calibration before any slow factor
        self._seeded: set[str] = set()  # parts given their own generator from self.rng

    # -- wiring (as FaultInjector's, kept live) -------------------------------------------------------
    def link(self, send_at: Callable[[int, bytes], None]) -> LiveFaultyLink:
        link = LiveFaultyLink(send_at, self.spec, np.random.default_rng(self.rng.integers(2**63)),
                              lambda: self.survey_t0_ns)
        self.links.append(link)
        return link

    def range_at(self, true_range_at: Callable[[int], float | None]) -> Callable[[int], float | None]:
        """Glitch readings mixed in at the percentage in force at each acquisition."""
        rng = np.random.default_rng(self.rng.integers(2**63))

        def glitchy(t_ns: int) -> float | None:
            p = self.spec.lidar_glitch_pct
            if p and rng.random() * 100 < p:
                self.counters["lidar_glitches"] += 1
                return GLITCH_RANGE_M if rng.random() < 0.5 else 0.01
            return true_range_at(t_ns)
        return glitchy

    def attach(self, bus, lidar, servo) -> None:
        self._servo_cal0 = servo.cal
        super().attach(bus, lidar, servo)
        self._seeded = {part for part, pct in (("bus", self.spec.i2c_nack_pct), ("lidar", self.spec.lidar_garbage_pct))
                        if pct}

    @property
    def has_devices(self) -> bool:
        return self._bus is not None

    def tick(self, now_ns: int) -> None:
        super().tick(now_ns)
        if self.busy_until_ns is not None and self._lidar is not None:
            if now_ns >= self.busy_until_ns:
                self.busy_until_ns = None
                self._lidar.stuck_busy = self._spec_busy(now_ns)
            else:
                self._lidar.stuck_busy = True

    def _spec_busy(self, now_ns: int) -> bool:
        t, w = self.t_s(now_ns), self.spec.lidar_stuck_busy
        return t is not None and w is not None and w[0] <= t < w[0] + w[1]

    # -- live changes ---------------------------------------------------------------------------------
    def update(self, **settings) -> None:
        """Change FaultSpec settings now (ValueError: a bad value, nothing changed).

        The links read the new spec at their next packet; the bus, LiDAR and servo are set at once (a
        new servo dead time applies to the pulses that follow, pulses already waiting keep theirs).
        """
        spec = replace(self.spec, **settings)  # validates
        self.spec = spec
        for link in self.links:
            link.spec = spec
        if self._bus is None:
            return
        for part, pct, obj in (("bus", spec.i2c_nack_pct, self._bus), ("lidar", spec.lidar_garbage_pct, self._lidar)):
            if pct and part not in self._seeded:
                obj.rng = np.random.default_rng(self.rng.integers(2**63))
                self._seeded.add(part)
        self._bus.nack_probability = spec.i2c_nack_pct / 100.0
        self._lidar.garbage_reads = spec.lidar_garbage_pct / 100.0
        slow = replace(self._servo_cal0, slew_rad_s=self._servo_cal0.slew_rad_s * spec.servo_slow_factor)
        self._servo.cal = slow
        self._servo.model.cal = slow
        self._servo.delay_ns = round(spec.servo_delay_ms * 1e6)

    def _count(self, name: str) -> None:
        self.counters[name] = self.counters.get(name, 0) + 1

    def outage_now(self, now_ns: int, duration_s: float) -> None:
        """Both link directions silent for duration_s, from just after now_ns (what goes out at now_ns
        itself, the acknowledgement of the request, still goes); 0 ends an outage in progress."""
        _check_seconds("outage", duration_s)
        window = (now_ns + 1, now_ns + 1 + round(duration_s * 1e9)) if duration_s > 0 else None
        for link in self.links:
            link.outage_ns = window
        if window is not None:
            self._count("link_outages")

    def outage_left_s(self, now_ns: int) -> float:
        ends = [w[1] for w in (link.outage_ns for link in self.links) if w is not None]
        return max(0.0, (max(ends) - now_ns) / 1e9) if ends else 0.0

    def stuck_busy_now(self, now_ns: int, duration_s: float) -> None:
        """The LiDAR's busy flag sticks for duration_s from now; 0 frees it (unless the spec's window holds)."""
        _check_seconds("stuck busy", duration_s)
        self.busy_until_ns = now_ns + round(duration_s * 1e9) if duration_s > 0 else None
        self._lidar.stuck_busy = self.busy_until_ns is not None or self._spec_busy(now_ns)
        if duration_s > 0:
            self._count("lidar_stuck_busy")

    def busy_left_s(self, now_ns: int) -> float:
        return 0.0 if self.busy_until_ns is None else max(0.0, (self.busy_until_ns - now_ns) / 1e9)

    def power_glitch_now(self) -> None:
        self._lidar.power_glitch()
        self.counters["power_glitches"] += 1

    @property
    def servo_stuck(self) -> bool:
        return self._servo is not None and bool(self._servo.stuck)

    def set_servo_stuck(self, stuck: bool) -> None:
        """The shaft stops where it is now (True) or moves again (False)."""
        if stuck and not self._servo.stuck:
            self.counters["servo_stuck"] += 1
        self._servo.stuck = bool(stuck)

    def reboot_now(self, silent_s: float) -> None:
        if self.reboot is None:
            raise ValueError("no autopilot to reboot")
        self.reboot(silent_s)
        self.counters["autopilot_reboots"] += 1


def _check_seconds(what: str, s: float) -> None:
    if not (math.isfinite(s) and s >= 0):
        raise ValueError(f"{what} must be >= 0 s, got {s!r}")


class FaultParams:
    """The SIM_PS_* parameters of a LiveFaultInjector: `MavlinkVehicleServer(..., extra_params=FaultParams(...))`.

    now_ns: the time the injector's links and timers run on (the vehicle's simulated time in `serve`).
    lock: held while the injection changes (the networked devices' lock: the bridge thread uses them).
    """

    def __init__(self, injector: LiveFaultInjector, now_ns: Callable[[], int], lock=None) -> None:
        self.injector, self._now_ns = injector, now_ns
        self._lock = lock if lock is not None else contextlib.nullcontext()

    def _available(self, p: SimParam) -> bool:
        inj = self.injector
        return {"link": bool(inj.links), "autopilot": inj.reboot is not None, "devices": inj.has_devices}[p.part]

    def names(self) -> list[str]:
        return [p.name for p in PARAMS if self._available(p)]

    def _param(self, name: str) -> SimParam:
        p = BY_NAME.get(name)
        if p is None or not self._available(p):
            raise KeyError(f"unknown parameter {name!r}")
        return p

    def get(self, name: str) -> float:
        p, inj = self._param(name), self.injector
        if p.field is not None:
            return float(getattr(inj.spec, p.field))
        if name == "SIM_PS_OUTAGE":
            return inj.outage_left_s(self._now_ns())
        if name == "SIM_PS_BUSY":
            return inj.busy_left_s(self._now_ns())
        if name == "SIM_PS_SRV_STK":
            return float(inj.servo_stuck)
        return 0.0  # SIM_PS_REBOOT, SIM_PS_PWRGLT: done when set

    def set(self, name: str, value: float) -> float | None:
        """Apply at once; KeyError for an unknown name, ValueError for a bad value (nothing changed).

        Returns what the acknowledging PARAM_VALUE carries: an action's value as set (a ground station
        re-sends a set until its value comes back: reading 0 at once would reboot or glitch again),
        None for a setting (read back).
        """
        p, inj = self._param(name), self.injector
        v = float(value)
        if p.flag and v not in (0.0, 1.0):
            raise ValueError(f"{value:g}: must be 0 or 1")
        if not (math.isfinite(v) and p.lo <= v <= p.hi):
            raise ValueError(f"{value:g} is outside {p.lo:g}..{p.hi:g}{' ' + p.unit if p.unit else ''}")
        with self._lock:
            now = self._now_ns()
            if p.field is not None:
                inj.update(**{p.field: v})
            elif name == "SIM_PS_OUTAGE":
                inj.outage_now(now, v)
            elif name == "SIM_PS_REBOOT":
                if v > 0:
                    inj.reboot_now(v)
            elif name == "SIM_PS_BUSY":
                inj.stuck_busy_now(now, v)
            elif name == "SIM_PS_PWRGLT":
                if v:
                    inj.power_glitch_now()
            elif name == "SIM_PS_SRV_STK":
                inj.set_servo_stuck(bool(v))
        return None if p.field is not None else v

