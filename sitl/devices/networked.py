"""Networked SITL: the emulated LIDAR-Lite and servo behind a TCP device bridge, in real time.

`pilescan-sitl serve --devices tcp:HOST:PORT` runs this next to the MAVLink autopilot, so an
unchanged `pilescan-payload --hal sitl:HOST:PORT` in another process (or on another machine) drives
the servo and ranges the simulated building as it would the real parts on I2C and PWM.
With `--rangefinder tfmini` an emulated TFMini also streams its frames into a pseudo-terminal
(`sitl.devices.tfmini_emu.PtyTfmini`): the payload opens it as `--uart serial:/dev/pts/N` and reads
it with pyserial, the code path of a Raspberry Pi's UART; the servo stays on the bridge.

Time: the devices run on `WallSimClock`, the vehicle's simulated time paced by the wall clock
exactly as `run_realtime` paces the physics, so the LiDAR ray-casts the true pose at the instant a
trigger arrives. The true states of the last seconds are kept for that (the physics runs in the
main thread, the bridge answers in its own; one lock serialises them). Bus transfers cost no
simulated time here: they take real time on the network instead.

Faults (`serve --fault`, the SIM_PS_* parameters): `NetworkedFaults` puts a `FaultyTransport` under
the MAVLink server and a `sitl.faults.params.LiveFaultInjector` on the devices, all on the vehicle's
simulated time; timed faults count from the start of the mission (the vehicle first entering AUTO),
as in the lockstep runner. The payload is another process on its own clock and disk, so its power
cut, clock jump and full disk are not faults this side can inject (`NOT_NETWORKED`).
"""

from __future__ import annotations

import collections
import contextlib
import threading
import time
from collections.abc import Callable
from typing import Any

from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.servo_model import ServoCalibration
from sitl.devices.bridge_server import DeviceBridgeServer, parse_bridge_url
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import ADDRESS, EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo
from sitl.devices.tfmini_emu import PtyTfmini
from sitl.faults.injector import FaultInjector, FaultSpec
from sitl.faults.params import FaultParams, LiveFaultInjector
from sitl.mavlink.server import MavlinkVehicleServer
from sitl.mavlink.transport import Transport
from sitl.runners.lockstep_payload import TrueBeam, TruePose, plant_state_of, pose_from_history
from sitl.sensing.noise import RangeNoise
from sitl.vehicle.api import FlightMode, Vehicle
from sitl.world.raycast import World

SERVO_CHANNEL = 0
"""The bridge's PWM channel wired to the emulated servo (`pilescan-payload --hal` uses channel 0)."""

LINK_FAULTS = frozenset({"link_loss_pct", "link_dup_pct", "link_reorder_pct", "link_outage", "link_latency_ms",
                         "link_jitter_ms", "autopilot_reboot"})
"""FaultSpec faults the networked SITL injects on its MAVLink side."""
DEVICE_FAULTS = frozenset({"i2c_nack_pct", "lidar_stuck_busy", "lidar_power_glitch_at_s", "lidar_garbage_pct",
                           "lidar_glitch_pct", "servo_stuck_at_s", "servo_slow_factor", "servo_delay_ms",
                           "servo_offset_deg", "servo_scale_pct", "boresight_deg", "sweep_yaw_deg",
                           "tfmini_bad_frame_pct", "tfmini_garbage_pct", "tfmini_unplug"})
"""FaultSpec faults it injects in its emulated devices (so only with them)."""
NOT_NETWORKED = {
    "power_cut_at_s": "the payload is another process (stop it yourself to cut its power)",
    "clock_jump": "the payload's clock is the companion computer's own real clock",
    "disk_full_at_s": "the payload writes to its own disk, in another process",
}
"""Why the other FaultSpec faults cannot be injected from this side."""


def check_networked_faults(spec: FaultSpec, devices: bool) -> None:
    """ValueError naming the first fault of spec the networked SITL cannot inject (devices: it has them)."""
    for name in spec.active:
        if name in DEVICE_FAULTS and not devices:
            raise ValueError(f"fault {name} needs --devices (the emulated LiDAR and servo it acts on)")
        if name not in LINK_FAULTS and name not in DEVICE_FAULTS:
            reason = NOT_NETWORKED.get(name, "it is not modelled in the networked SITL")
            raise ValueError(f"fault {name} cannot be injected by serve: {reason}")


class WallSimClock:
    """The vehicle's simulated time (ns) as the wall clock advances: t0_sim + (wall - t0_wall) * speedup."""

    def __init__(self, t0_sim_s: float, speedup: float = 1.0,
                 mono_ns: Callable[[], int] = time.monotonic_ns) -> None:
        self._mono_ns, self.speedup = mono_ns, float(speedup)
        self._t0_wall_ns, self._t0_sim_ns = mono_ns(), round(t0_sim_s * 1e9)

    def now_ns(self) -> int:
        return self._t0_sim_ns + round((self._mono_ns() - self._t0_wall_ns) * self.speedup)

    def sleep_until_ns(self, t_ns: int) -> None:
        delay_ns = (t_ns - self.now_ns()) / self.speedup
        if delay_ns > 0:
            time.sleep(delay_ns / 1e9)

    def advance_by_ns(self, dt_ns: int) -> None:
        """Wire time passes for real on the network; nothing to add."""

    def at_monotonic_ns(self, mono_ns: int) -> int:
        """The simulated time (ns) at an instant of the monotonic clock (the pty TFMini's frame times)."""
        return self._t0_sim_ns + round((mono_ns - self._t0_wall_ns) * self.speedup)


class NetworkedDevices:
    """The emulated LiDAR (I2C 0x62) and servo (PWM channel 0) of one vehicle, served over TCP.

    Call `record()` after every physics step (run_realtime's on_step) and `close()` at the end.
    """

    def __init__(self, vehicle: Vehicle, world: World, url: str, *, frame: StorageFrame | None = None,
                 lever_arm_body_m=(0.0, 0.0, 0.10), speedup: float = 1.0, keep_s: float = 5.0,
                 servo_cal: ServoCalibration | None = None, range_noise_sigma_m: float = 0.0,
                 key: bytes | None = None, rangefinder: Rangefinder = Rangefinder.LIDARLITE_V3) -> None:
        host, port = parse_bridge_url(url)
        self.vehicle, self.world = vehicle, world
        self.frame = frame or StorageFrame()
        self.lever = tuple(float(v) for v in lever_arm_body_m)
        self.lock = threading.RLock()
        self._hist: collections.deque[tuple[float, tuple[float, ...]]] = collections.deque(
            maxlen=max(2, round(keep_s / vehicle.dt_s)))
        self.record()
        self.clock = WallSimClock(vehicle.state().t_s, speedup)
        self.servo = EmulatedServo(self.clock, servo_cal)
        # The true beam: pose, shaft (+ a noise model's servo error), mounting (a boresight fault tilts it).
        self.beam = TrueBeam(world, self.frame, self.lever, self.pose_at, self.servo.angle_at)
        self.lidar = EmulatedLidarLite(self.clock, self.range_at, range_noise_sigma_m=range_noise_sigma_m)
        self.bus = SimI2CBus(self.clock)
        self.bus.attach(ADDRESS, self.lidar)
        self.counters = {"ahead_of_physics": 0}
        self.bridge = DeviceBridgeServer(self.bus, {SERVO_CHANNEL: self.servo}, host, port, lock=self.lock,
                                         key=key)  # None: open to anyone who can reach the port
        self.tfmini: PtyTfmini | None = None
        if rangefinder is Rangefinder.TFMINI:
            self.tfmini = PtyTfmini(self._tfmini_range_at, rate_hz=rangefinder.spec.rate_hz)

    @property
    def url(self) -> str:
        return self.bridge.url

    def start(self) -> NetworkedDevices:
        self.bridge.start()
        if self.tfmini is not None:
            self.tfmini.start()
        return self

    def close(self) -> None:
        self.bridge.close()
        if self.tfmini is not None:
            self.tfmini.close()

    @property
    def tfmini_path(self) -> str | None:
        """The pseudo-terminal the emulated TFMini streams into (None without one)."""
        return self.tfmini.path if self.tfmini is not None else None

    def _tfmini_range_at(self, mono_ns: int) -> float | None:
        """What the TFMini sees at a frame's measurement (its thread's monotonic clock), under the lock the
        bridge and the physics share (the servo plant and the pose history)."""
        with self.lock:
            return self.lidar.range_at(self.clock.at_monotonic_ns(mono_ns))

    def __enter__(self) -> NetworkedDevices:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def record(self) -> None:
        """Keep the vehicle's true state after a physics step."""
        with self.lock:
            self._hist.append((self.vehicle.state().t_s, plant_state_of(self.vehicle)))

    def pose_at(self, t_ns: int) -> TruePose:
        with self.lock:
            if t_ns * 1e-9 > self._hist[-1][0]:
                self.counters["ahead_of_physics"] += 1  # the physics fell behind the wall clock
            return pose_from_history(self._hist, t_ns * 1e-9)

    @property
    def boresight(self) -> Boresight:
        """The beam's true mounting (a boresight fault tilts it)."""
        return self.beam.boresight

    @boresight.setter
    def boresight(self, b: Boresight) -> None:
        self.beam.boresight = b

    def range_at(self, t_ns: int) -> float | None:
        """What the LiDAR sees at simulated time t_ns: the true pose and shaft angle, ray traced."""
        return self.beam.range_m(t_ns)

    def attach_noise(self, noise: RangeNoise | None) -> None:
        """The rangefinder's noise model (`sitl.runners.lockstep_payload.attach_sensor_noise` gives it): the
        LIDAR-Lite's on the bridge, and the TFMini's on its pty when there is one."""
        with self.lock:
            self.lidar.range_noise = noise
            if self.tfmini is not None:
                self.tfmini.source.range_noise = noise

    def attach_faults(self, injector: FaultInjector) -> None:
        """Inject injector's device faults here: glitch readings in the ranges, NACKs on the bus, the
        LiDAR's and servo's fault knobs (call it before start(), or it waits for the lock)."""
        with self.lock:
            self.lidar.range_at = injector.range_at(self.range_at)
            injector.attach(self.bus, self.lidar, self.servo)
            if self.tfmini is not None:
                injector.attach_tfmini(self.tfmini)
            self.boresight = injector.boresight


_EVERYONE = object()


class FaultyTransport:
    """A MAVLink Transport with link faults both ways, on simulated time: wraps the server's `inner`.

    Every packet the server sends (down) and every datagram it receives (up) goes through a FaultyLink
    of `injector` (loss, duplication, reordering, outage, latency and jitter); packets not yet due wait
    in a time-ordered queue per direction. The server calls recv() at every update, which flushes
    both, so they go out within a physics step of their time. Latency and jitter keep the order, as
    the lockstep runner's link does. A listening UDP transport learns a client when one of its
    datagrams is delivered (a lost one teaches it nothing); `recv_datagrams` and `add_peer` are there
    when the inner transport has them (the signed server uses them).
    """

    def __init__(self, inner: Transport, injector: FaultInjector, now_ns: Callable[[], int]) -> None:
        self.inner, self._now_ns = inner, now_ns
        self._down_q: collections.deque[tuple[int, tuple[bytes, Any]]] = collections.deque()
        self._up_q: collections.deque[tuple[int, tuple[bytes, Any]]] = collections.deque()
        self.down = injector.link(self._queue(self._down_q))  # autopilot -> clients (as the runner's "down")
        self.up = injector.link(self._queue(self._up_q))
        if hasattr(inner, "recv_datagrams"):
            self.recv_datagrams = self._recv_datagrams

    @staticmethod
    def _queue(q: collections.deque) -> Callable[[int, Any], None]:
        def send_at(t_ns: int, item: Any) -> None:
            q.append((max(t_ns, q[-1][0]) if q else t_ns, item))  # never ahead of what is waiting
        return send_at

    def send(self, data: bytes) -> None:
        self.down.send_at(self._now_ns(), (bytes(data), _EVERYONE))
        self.flush()

    def send_to(self, data: bytes, peer: Any) -> None:
        """A reply to one sender, through the same faulted down link (when the inner transport can address one)."""
        self.down.send_at(self._now_ns(), (bytes(data), peer if hasattr(self.inner, "send_to") else _EVERYONE))
        self.flush()

    def flush(self) -> None:
        """Send the packets now due."""
        now = self._now_ns()
        while self._down_q and self._down_q[0][0] <= now:
            data, peer = self._down_q.popleft()[1]
            if peer is _EVERYONE:
                self.inner.send(data)
            else:
                self.inner.send_to(data, peer)

    def _arrived(self) -> list[tuple[bytes, Any]]:
        """What the inner transport received, through the up link; then what is due now, with its sender."""
        now = self._now_ns()
        if hasattr(self.inner, "recv_datagrams"):
            for data, addr in self.inner.recv_datagrams():
                self.up.send_at(now, (data, addr))
        else:
            data = self.inner.recv()
            if data:
                self.up.send_at(now, (data, None))
        due = []
        while self._up_q and self._up_q[0][0] <= now:
            due.append(self._up_q.popleft()[1])
        return due

    def recv(self) -> bytes:
        self.flush()
        got = self._arrived()
        for _data, addr in got:
            if addr is not None:
                self.inner.add_peer(addr)
        return b"".join(data for data, _addr in got)

    def _recv_datagrams(self) -> list[tuple[bytes, Any]]:
        self.flush()
        return self._arrived()

    def add_peer(self, addr: Any) -> bool:
        """The inner transport's answer: False when its client table is full."""
        return self.inner.add_peer(addr) is not False

    def close(self) -> None:
        self.inner.close()

    def __getattr__(self, name: str) -> Any:  # local_address, peers, dropped_packets ...
        inner = self.__dict__.get("inner")
        if inner is None:
            raise AttributeError(name)
        return getattr(inner, name)


class NetworkedFaults:
    """Fault injection in the networked SITL (`serve --fault`, the SIM_PS_* parameters).

    Give the server `transport` (the faulted MAVLink link) and `params` (as extra_params), then
    `bind(server)`; call `step()` after every physics step: it starts the fault clock when the vehicle
    first enters AUTO (the mission starts), fires the timed faults and flushes delayed packets. Time
    is the vehicle's simulated time, as the devices' clock.
    """

    def __init__(self, spec: FaultSpec, vehicle: Vehicle, transport: Transport,
                 devices: NetworkedDevices | None = None) -> None:
        self.vehicle, self.devices = vehicle, devices
        self.injector = LiveFaultInjector(spec)
        self.transport = FaultyTransport(transport, self.injector, self.now_ns)
        self._lock = devices.lock if devices is not None else contextlib.nullcontext()
        if devices is not None:
            devices.attach_faults(self.injector)
        self.params = FaultParams(self.injector, self.now_ns, lock=devices.lock if devices is not None else None)

    def now_ns(self) -> int:
        return round(self.vehicle.state().t_s * 1e9)

    def bind(self, server: MavlinkVehicleServer) -> None:
        """The autopilot that reboots (autopilot_reboot, SIM_PS_REBOOT)."""
        self.injector.reboot = server.reboot

    def step(self) -> None:
        inj, now = self.injector, self.now_ns()
        if inj.survey_t0_ns is None and self.vehicle.state().mode == FlightMode.AUTO:
            inj.start_survey(now)
        with self._lock:
            inj.tick(now)
        self.transport.flush()

    def summary(self) -> str:
        """What was injected, for the operator (empty when nothing was)."""
        parts = []
        for label, c in (("MAVLink out", self.transport.down.counters), ("in", self.transport.up.counters)):
            what = [f"{v} {k.replace('_', ' ')}" for k, v in c.items() if v and k != "packets"]
            if what:
                parts.append(f"{label} {c['packets']} packets: {', '.join(what)}")
        counters = dict(self.injector.counters)
        if self.devices is not None:
            counters["I2C_NACKs"] = self.devices.bus.counters["nack"]
            if self.devices.tfmini is not None:
                src = self.devices.tfmini.source
                counters["TFMini_bad_frames_sent"] = src.bad_frames_sent
                counters["TFMini_garbage_bursts"] = src.garbage_bursts
        parts += [f"{k.replace('_', ' ')} {v}" for k, v in counters.items() if v]
        return "; ".join(parts)
