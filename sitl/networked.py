"""Networked SITL: the emulated LIDAR-Lite and servo behind a TCP device bridge, in real time.

`pilescan-sitl serve --devices tcp:HOST:PORT` runs this next to the MAVLink autopilot, so an
unchanged `pilescan-payload --hal sitl:HOST:PORT` in another process (or on another machine) drives
the servo and ranges the simulated building as it would the real parts on I2C and PWM.

Time: the devices run on `WallSimClock`, the vehicle's simulated time paced by the wall clock
exactly as `run_realtime` paces the physics, so the LiDAR ray-casts the true pose at the instant a
trigger arrives. The true states of the last seconds are kept for that (the physics runs in the
main thread, the bridge answers in its own; one lock serialises them). Bus transfers cost no
simulated time here: they take real time on the network instead.
"""

from __future__ import annotations

import collections
import threading
import time
from collections.abc import Callable

from firmware_py.drivers.servo import ServoCalibration
from firmware_py.frames import StorageFrame
from sitl.devices.bridge_server import DeviceBridgeServer, parse_bridge_url
from sitl.devices.i2c_sim import SimI2CBus
from sitl.devices.lidarlite_emu import ADDRESS, EmulatedLidarLite
from sitl.devices.servo_emu import EmulatedServo
from sitl.payload_runner import TruePose, beam_range_m, pose_from_history, state_tuple
from sitl.raycast import World
from sitl.vehicle_api import Vehicle

SERVO_CHANNEL = 0
"""The bridge's PWM channel wired to the emulated servo (`pilescan-payload --hal` uses channel 0)."""


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


class NetworkedDevices:
    """The emulated LiDAR (I2C 0x62) and servo (PWM channel 0) of one vehicle, served over TCP.

    Call `record()` after every physics step (run_realtime's on_step) and `close()` at the end.
    """

    def __init__(self, vehicle: Vehicle, world: World, url: str, *, frame: StorageFrame | None = None,
                 lever_arm_body_m=(0.0, 0.0, 0.10), speedup: float = 1.0, keep_s: float = 5.0,
                 servo_cal: ServoCalibration | None = None, range_noise_sigma_m: float = 0.0) -> None:
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
        self.lidar = EmulatedLidarLite(self.clock, self.range_at, range_noise_sigma_m=range_noise_sigma_m)
        self.bus = SimI2CBus(self.clock)
        self.bus.attach(ADDRESS, self.lidar)
        self.counters = {"ahead_of_physics": 0}
        self.bridge = DeviceBridgeServer(self.bus, {SERVO_CHANNEL: self.servo}, host, port, lock=self.lock)

    @property
    def url(self) -> str:
        return self.bridge.url

    def start(self) -> NetworkedDevices:
        self.bridge.start()
        return self

    def close(self) -> None:
        self.bridge.close()

    def __enter__(self) -> NetworkedDevices:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()

    def record(self) -> None:
        """Keep the vehicle's true state after a physics step."""
        with self.lock:
            self._hist.append((self.vehicle.state().t_s, state_tuple(self.vehicle)))

    def pose_at(self, t_ns: int) -> TruePose:
        with self.lock:
            if t_ns * 1e-9 > self._hist[-1][0]:
                self.counters["ahead_of_physics"] += 1  # the physics fell behind the wall clock
            return pose_from_history(self._hist, t_ns * 1e-9)

    def range_at(self, t_ns: int) -> float | None:
        """What the LiDAR sees at simulated time t_ns: the true pose and shaft angle, ray traced."""
        return beam_range_m(self.world, self.frame, self.lever, self.pose_at(t_ns), self.servo.angle_at(t_ns))
