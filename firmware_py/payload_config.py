"""What `pilescan-payload` can be told, checked: `PayloadConfig`, the payload's one configuration record (the command
line's options and the configuration file's `[payload]` and `[site]` end here), its defaults for a Raspberry Pi with a
LIDAR-Lite v3 on I2C bus 1, and what it writes into the sample log's header (the sensor, the hardware, the effective
configuration). Every value is checked when the record is made, so a mistake is refused before anything is opened;
`firmware_py.app` builds the program from it."""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import asdict, dataclass, field
from typing import Any

from firmware_py.core.frames import SQUARE, Boresight, StorageFrame
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.header import build_log_header, sensor_spec
from firmware_py.core.numbers import is_finite_number
from firmware_py.core.pose_source import HEADER_KEY as POSE_SOURCE_KEY
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.servo_model import PWM_FRAME_S, ServoCalibration
from firmware_py.core.site import Site
from firmware_py.core.storage import Storage
from firmware_py.core.stream_format import MAX_RECORDS, parse_stream_url
from firmware_py.core.waveform import Waveform, named_waveform
from firmware_py.drivers.lidarlite import (
    DEFAULT_ADDRESS,
    PRESET_FAST_500HZ,
    busy_deadline_ns,
    preset_by_name,
)
from firmware_py.drivers.tfmini import TfminiConfig
from firmware_py.hal.backends import check_i2c_url
from firmware_py.hal.bridge import check_bridge_key
from firmware_py.hal.mavlink_link import check_mavlink_url
from firmware_py.hal.pwm import check_pwm_url
from firmware_py.hal.signing import SigningConfig
from firmware_py.hal.uart import DEFAULT_BAUD, check_uart_url, parse_uart_url
from firmware_py.payload import LoopConfig
from firmware_py.pose import set_gps_global_origin_msg
from firmware_py.pose_tracker import PoseTrackerConfig

DEFAULT_MAVLINK_URL = "udpout:127.0.0.1:14550"
DEFAULT_I2C_URL = "i2c:1"
DEFAULT_PWM_URL = "pwm:sysfs:0:0"
DEFAULT_UART_URL = "serial:/dev/serial0:115200"
"""The Raspberry Pi's header UART (GPIO 14 TX, 15 RX) at the TFMini's factory rate."""
DEFAULT_RANGEFINDER = Rangefinder.LIDARLITE_V3
DEFAULT_PRESET = PRESET_FAST_500HZ.name
MAX_EKF_ORIGIN_OFFSET_M = 10_000.0
"""How far the EKF origin sent may be from the site's corner: the local NED frame is a flat-earth tangent
plane about it, fit for a building's neighbourhood; farther is a mistake (two different places typed)."""


def _deg(rad: float) -> float:
    """Degrees as a person wrote them: 1.5, not the 1.5000000000000002 a round trip through radians gives."""
    return float(f"{math.degrees(rad):.12g}")


@dataclass(frozen=True)
class PayloadConfig:
    """Everything `pilescan-payload` can be told (CLI options in brackets).

    Attributes:
        out_path: the sample log to write [--out]; never overwritten unless `force` [--force].
        mavlink_url: link to the autopilot [--mavlink]: serial:/dev/ttyAMA0:921600, udp:HOST:PORT,
            udpout:HOST:PORT, tcp:HOST:PORT, or a registered scheme.
        rangefinder: which rangefinder is fitted [--rangefinder]: the LIDAR-Lite v3 on I2C (`i2c_url`)
            or a TFMini on a UART (`uart_url`).
        i2c_url: the LIDAR-Lite's bus [--i2c]: i2c:1, i2c:/dev/i2c-1, tcp:HOST:PORT (SITL bridge), ...
        uart_url: the TFMini's serial port [--uart]: serial:/dev/PATH[:BAUD] (the Pi's header UART is
            /dev/serial0; the networked SITL's emulated part is a /dev/pts/N).
        pwm_url: the servo's output [--pwm]: pwm:sysfs:CHIP:CH, pwm:pca9685:BUS:ADDR:CH, pwm:mavlink:N,
            pwm:tcp:HOST:PORT:CH (SITL bridge), ...
        preset: LIDAR-Lite register preset name [--preset] (`firmware_py.drivers.lidarlite.PRESETS`).
        i2c_address: the LIDAR-Lite's 7-bit address.
        rate_hz: payload loop / LiDAR sample rate, Hz [--rate]; None: the rangefinder's own (500 Hz
            LIDAR-Lite, 100 Hz TFMini). A TFMini streams at the rate it is set to: this says which.
        sensor_start_timeout_s: a TFMini must send a valid frame within this long of opening its port,
            or the program stops with a line saying what it saw (nothing, or bytes but no frames).
        waveform, servo_peak_rate_rad_s, initial_position: the eq. (1) sweep
            [--waveform, --servo-rate, --phase], as `pilescan-sitl fly`.
        servo: pulse-width calibration and dynamics of the servo.
        storage: building L x W x H [--storage]; frame: its placement in local NED.
        site: where the building stands on Earth [--origin, --heading] (`firmware_py.core.site`), written
            to the header; None = not known. With send_origin, frame must be the site about it.
        lever_arm_body_m: sensor position from the centre of gravity, body FRD, m [--lever-arm].
        boresight: how the beam's mounting differs from square [--boresight TILT_DEG SWEEP_YAW_DEG]; written
            to the header, where the ground station places points with it.
        range_sigma_m, range_sigma_rel: the sensor's range error model written to the header (the
            ground station sizes its wall tolerances with it); None: the rangefinder's datasheet.
        duration_s: stop after sampling this long (from the first sample); None = until stopped [--duration].
        stop_on_disarm: stop when the autopilot disarms after having been armed [--stop-on-disarm].
        start_on_arm: open the log and start the sweep only once the autopilot's HEARTBEAT shows armed
            [--start-on-arm]; stopped before that, the payload writes no log. With stop_on_disarm and a
            service manager that starts the payload again when it stops, one log per flight.
        stream_url: live sample stream to the ground, udp:HOST:PORT; None = off [--stream].
        stream_records_per_datagram: records batched per datagram.
        signing: MAVLink 2 signing of the autopilot link, and authentication of the live stream with
            the same key [--signing-key FILE, --allow-unsigned]; None = off.
        device_key: the 32-byte key the device bridge (tcp: / pwm:tcp: URLs, --hal sitl:) authenticates
            with [--signing-key FILE with --hal or bridge URLs]; ignored by local buses; None = off.
        send_origin: (lat deg, lon deg, alt m MSL) sent as SET_GPS_GLOBAL_ORIGIN at start [--send-origin].
        mission_id: ties the log to a mission plan [--mission-id].
        target_system, target_component: the autopilot's MAVLink ids.
        pose_stream_hz: ATTITUDE / LOCAL_POSITION_NED rate asked of the autopilot.
        max_pose_age_s, max_pose_wait_s: `LoopConfig`'s pose limits.
        records_per_block: records per fsync'd log block (a power cut loses at most one block).
        fsync: fsync every block (off only for tests).
        health_period_s: NAMED_VALUE_FLOAT period, s.
        status_period_s: progress line period on stderr, s.
        quiet: no progress or summary lines (warnings and errors still print) [--quiet].
        wait_for_pose_s: before the first sample, wait up to this long for a trusted pose (time sync
            converged and a fresh pose from the autopilot), pumping the link, so the log does not open
            with samples that cannot be posed; 0 = start sampling at once. The lockstep SITL waits.
        param_wait_s: before the first sample, wait up to this long for the autopilot's EKF source parameters
            (`firmware_py.core.pose_source`), which the header keeps so the ground station can say what the pose
            came from; cut short at 1 s when nothing has come from the autopilot. 0 = do not wait.
        source, mission: the header's provenance and what was flown (the SITL writes its mission
            plan there; the drone's program does not know it).
        config_file: the configuration file the options started from [--config], for the header's
            ``config`` record; None: none.
        signing_key_file: the key file's path [--signing-key], recorded there (never the key).
        header_extra: further header keys, written after the payload's own (the SITL states there the
            sensor noise it simulates, ``sensor_noise``); they may not replace a key the payload writes.
    """

    out_path: str | os.PathLike[str] = "samples.pslog"
    force: bool = False
    mavlink_url: str = DEFAULT_MAVLINK_URL
    rangefinder: Rangefinder = DEFAULT_RANGEFINDER
    i2c_url: str = DEFAULT_I2C_URL
    uart_url: str = DEFAULT_UART_URL
    pwm_url: str = DEFAULT_PWM_URL
    preset: str = DEFAULT_PRESET
    i2c_address: int = DEFAULT_ADDRESS
    rate_hz: float | None = None
    sensor_start_timeout_s: float = 1.0
    waveform: str = "semi-triangular"
    servo_peak_rate_rad_s: float = 5.0
    initial_position: int = 0
    servo: ServoCalibration = field(default_factory=ServoCalibration)
    storage: Storage = field(default_factory=Storage)
    frame: StorageFrame = field(default_factory=StorageFrame)
    site: Site | None = None
    lever_arm_body_m: tuple[float, float, float] = (0.0, 0.0, 0.10)
    boresight: Boresight = SQUARE
    range_sigma_m: float | None = None
    range_sigma_rel: float | None = None
    duration_s: float | None = None
    stop_on_disarm: bool = False
    start_on_arm: bool = False
    stream_url: str | None = None
    stream_records_per_datagram: int = 20
    signing: SigningConfig | None = None
    device_key: bytes | None = field(default=None, repr=False)
    send_origin: tuple[float, float, float] | None = None
    mission_id: str | None = None
    target_system: int = 1
    target_component: int = 1
    pose_stream_hz: float = 50.0
    max_pose_age_s: float = 0.1
    max_pose_wait_s: float = 0.25
    records_per_block: int = 500
    fsync: bool = True
    health_period_s: float = 1.0
    status_period_s: float = 5.0
    quiet: bool = False
    wait_for_pose_s: float = 0.0
    param_wait_s: float = 3.0
    source: str = "payload"
    mission: Mapping[str, Any] | None = None
    config_file: str | None = None
    signing_key_file: str | None = None
    header_extra: Mapping[str, Any] | None = None

    def busy_deadline_ns(self) -> int:
        """The LiDAR's busy deadline at this rate (a stuck part must not stop the loop keeping it)."""
        if not is_finite_number(self.rate_hz) or self.rate_hz <= 0:
            raise ValueError(f"payload rate must be 1-2000 Hz, got {self.rate_hz!r}")
        return busy_deadline_ns(preset_by_name(self.preset), self.rate_hz)

    def __post_init__(self) -> None:
        if not isinstance(self.rangefinder, Rangefinder):
            raise ValueError(f"rangefinder must be one of {', '.join(r.value for r in Rangefinder)}, "
                             f"got {self.rangefinder!r}")
        spec = self.rangefinder.spec  # unset rate and error model: the fitted rangefinder's datasheet
        for name, default in (("rate_hz", spec.rate_hz), ("range_sigma_m", spec.range_sigma_m),
                              ("range_sigma_rel", spec.range_sigma_rel)):
            if getattr(self, name) is None:
                object.__setattr__(self, name, default)
        if not isinstance(self.out_path, str | os.PathLike) or not str(self.out_path).strip():
            raise ValueError(f"sample log path must be a non-empty path, got {self.out_path!r}")
        self._check_urls()
        if self.rangefinder is Rangefinder.TFMINI:
            self.tfmini_config()  # the frame rate fits the baud rate
            if not (is_finite_number(self.sensor_start_timeout_s) and 0.0 < self.sensor_start_timeout_s <= 60.0):
                raise ValueError(f"sensor start timeout must be in (0, 60] s, got {self.sensor_start_timeout_s!r}")
        else:
            self.busy_deadline_ns()  # the preset exists and can sustain the rate
        if isinstance(self.i2c_address, bool) or not isinstance(self.i2c_address, int) \
                or not 0x08 <= self.i2c_address <= 0x77:
            raise ValueError(f"I2C address must be a 7-bit address 0x08-0x77, got {self.i2c_address!r}")
        self.loop_config()  # rate and pose ages
        if not (is_finite_number(self.max_pose_wait_s) and 0.0 < self.max_pose_wait_s <= 10.0):
            raise ValueError(f"max pose wait must be in (0, 10] s, got {self.max_pose_wait_s!r}")
        self.servo_waveform()  # name, rate, initial position
        if not isinstance(self.servo, ServoCalibration):
            raise ValueError(f"servo must be a ServoCalibration, got {self.servo!r}")
        if not isinstance(self.storage, Storage) or not isinstance(self.frame, StorageFrame):
            raise ValueError("storage and frame must be a Storage and a StorageFrame")
        lever = tuple(self.lever_arm_body_m)
        if len(lever) != 3 or not all(is_finite_number(v) for v in lever):
            raise ValueError(f"lever arm must be 3 finite numbers (x y z, m), got {self.lever_arm_body_m!r}")
        if not isinstance(self.boresight, Boresight):
            raise ValueError(f"boresight must be a Boresight, got {self.boresight!r}")
        self.sensor()  # the error model
        if self.duration_s is not None and not (is_finite_number(self.duration_s) and self.duration_s > 0):
            raise ValueError(f"duration must be > 0 s, got {self.duration_s!r}")
        if self.stream_url is not None:
            parse_stream_url(self.stream_url)
        n = self.stream_records_per_datagram
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= MAX_RECORDS:
            raise ValueError(f"records per datagram must be 1-{MAX_RECORDS}, got {n!r}")
        if self.signing is not None and not isinstance(self.signing, SigningConfig):
            raise ValueError(f"signing must be a SigningConfig, got {type(self.signing).__name__}")
        check_bridge_key(self.device_key)
        if self.send_origin is not None:
            if len(tuple(self.send_origin)) != 3:
                raise ValueError(f"EKF origin must be LAT LON ALT, got {self.send_origin!r}")
            set_gps_global_origin_msg(*self.send_origin)  # range checks
        self._check_site()
        if self.mission_id is not None and (not isinstance(self.mission_id, str) or not self.mission_id.strip()):
            raise ValueError(f"mission id must be a non-empty string, got {self.mission_id!r}")
        PoseTrackerConfig(target_system=self.target_system, target_component=self.target_component,
                          stream_hz=self.pose_stream_hz)
        n = self.records_per_block
        if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= 100_000:
            raise ValueError(f"records per block must be 1-100000, got {n!r}")
        if not (is_finite_number(self.wait_for_pose_s) and 0.0 <= self.wait_for_pose_s <= 3600.0):
            raise ValueError(f"pose wait must be 0-3600 s, got {self.wait_for_pose_s!r}")
        if not (is_finite_number(self.param_wait_s) and 0.0 <= self.param_wait_s <= 60.0):
            raise ValueError(f"parameter wait must be 0-60 s, got {self.param_wait_s!r}")
        if not isinstance(self.source, str) or not self.source.strip():
            raise ValueError(f"log source must be a non-empty string, got {self.source!r}")
        if self.header_extra is not None:
            if not isinstance(self.header_extra, Mapping):
                raise ValueError(f"header extra must be a mapping, got {type(self.header_extra).__name__}")
            self.log_header()  # a key clashing with the payload's own is refused here, not at the first sample
        for name in ("health_period_s", "status_period_s"):
            v = getattr(self, name)
            if not (is_finite_number(v) and 0.05 <= v <= 3600.0):
                raise ValueError(f"{name} must be 0.05-3600 s, got {v!r}")

    def _check_site(self) -> None:
        """The header's frame is the site's, about the EKF origin we send: a log must not carry two
        placements of the building that disagree."""
        if self.site is None:
            return
        if not isinstance(self.site, Site):
            raise ValueError(f"site must be a Site, got {self.site!r}")
        if self.send_origin is None:
            return
        want = self.site.frame_about(GeodeticPoint(*self.send_origin))
        off_m = math.hypot(want.origin_ned_m[0], want.origin_ned_m[1])
        if off_m > MAX_EKF_ORIGIN_OFFSET_M:
            raise ValueError(f"the EKF origin sent {tuple(self.send_origin)} is {off_m / 1000:.0f} km from the site's "
                             f"corner ({self.site.describe()}): it must be the building's neighbourhood (within "
                             f"{MAX_EKF_ORIGIN_OFFSET_M / 1000:g} km); leave the EKF origin out to send the corner")
        got = self.frame
        if not (math.isclose(got.heading_rad, want.heading_rad, abs_tol=1e-9)
                and all(math.isclose(a, b, abs_tol=1e-6) for a, b in zip(got.origin_ned_m, want.origin_ned_m,
                                                                          strict=True))):
            raise ValueError(f"storage frame {got.to_dict()} is not the site ({self.site.describe()}) about the "
                             f"EKF origin sent {tuple(self.send_origin)}: {want.to_dict()}")

    def _check_urls(self) -> None:
        for name, url in (("MAVLink", self.mavlink_url), ("I2C bus", self.i2c_url), ("PWM output", self.pwm_url)):
            if not isinstance(url, str) or not url.strip():
                raise ValueError(f"{name} URL must be a non-empty string like SCHEME:..., got {url!r}")
        # Each URL against its kind's schemes as this process knows them (built-in, or registered by another layer,
        # whose own options are checked when opened): an unknown scheme is refused here, not when the flight starts.
        check_mavlink_url(self.mavlink_url)
        check_i2c_url(self.i2c_url)
        check_pwm_url(self.pwm_url)  # before anything is opened
        if self.rangefinder is Rangefinder.TFMINI:
            if not isinstance(self.uart_url, str) or not self.uart_url.strip():
                raise ValueError(f"serial port URL must be a non-empty string like {DEFAULT_UART_URL}, "
                                 f"got {self.uart_url!r}")
            check_uart_url(self.uart_url)

    def loop_config(self) -> LoopConfig:
        if self.rangefinder.streams:
            return LoopConfig(rate_hz=self.rate_hz, max_pose_age_s=self.max_pose_age_s,
                              max_pose_wait_s=self.max_pose_wait_s, paced_by_sensor=True)
        return LoopConfig(rate_hz=self.rate_hz, max_pose_age_s=self.max_pose_age_s,
                          max_pose_wait_s=self.max_pose_wait_s)

    def uart_baud(self) -> int:
        """The baud rate in the serial URL (the factory rate for a port another layer provides)."""
        return parse_uart_url(self.uart_url)[1] if self.uart_url.split(":", 1)[0] == "serial" else DEFAULT_BAUD

    def tfmini_config(self) -> TfminiConfig:
        """The TFMini driver's settings: the URL's baud rate, our rate as the part's frame rate."""
        return TfminiConfig(baud=self.uart_baud(), frame_rate_hz=self.rate_hz)

    def servo_waveform(self) -> Waveform:
        return named_waveform(self.waveform, self.servo_peak_rate_rad_s, self.initial_position)

    def sensor(self) -> dict[str, Any]:
        """The header's sensor dict: the fitted rangefinder's datasheet at our rate (the LIDAR-Lite with
        its preset's modelled range), with the configured error model."""
        if self.rangefinder is Rangefinder.TFMINI:
            return self.rangefinder.spec.with_(rate_hz=self.rate_hz, range_sigma_m=self.range_sigma_m,
                                               range_sigma_rel=self.range_sigma_rel).to_dict()
        return sensor_spec(self.rate_hz, max_range_m=preset_by_name(self.preset).max_range_m,
                           range_sigma_m=self.range_sigma_m, range_sigma_rel=self.range_sigma_rel)

    def hardware(self) -> dict[str, Any]:
        """The header's ``payload``: the hardware the program was told to use."""
        if self.rangefinder is Rangefinder.TFMINI:
            return {"mavlink": self.mavlink_url, "rangefinder": self.rangefinder.value, "uart": self.uart_url,
                    "pwm": self.pwm_url, "rate_hz": self.rate_hz, "records_per_block": self.records_per_block}
        return {"mavlink": self.mavlink_url, "i2c": self.i2c_url, "pwm": self.pwm_url,
                "lidar_preset": self.preset, "i2c_address": self.i2c_address,
                "rate_hz": self.rate_hz, "records_per_block": self.records_per_block}

    def log_header(self, sweep_t0_s: float | None = None,
                   autopilot_params: Mapping[str, float] | None = None) -> dict[str, Any]:
        """The sample-log header (`firmware_py.core.header`), with the payload's hardware setup appended.

        sweep_t0_s: when the servo sweep starts, on the samples' clock; with the calibration it lets
        the ground station re-simulate the servo (`ground.servo_timing`) if the real one differs.
        autopilot_params: the autopilot's EKF source parameters as it answered them (`POSE_SOURCE_KEY`).
        """
        drive = {} if sweep_t0_s is None else {"servo_drive": {"t0_s": float(sweep_t0_s), "frame_s": PWM_FRAME_S}}
        if autopilot_params:
            drive[POSE_SOURCE_KEY] = dict(autopilot_params)
        return build_log_header(
            source=self.source, sensor=self.sensor(), lever_arm_body_m=[float(v) for v in self.lever_arm_body_m],
            waveform_name=self.waveform, waveform=self.servo_waveform(), initial_position=self.initial_position,
            storage=self.storage, frame=self.frame, mission_id=self.mission_id, mission=self.mission, site=self.site,
            extra={"servo_calibration": asdict(self.servo), "boresight": self.boresight.to_dict(),
                   "config": self.effective_config(), "payload": self.hardware(),
                   **drive, **self._header_extra()})

    def _header_extra(self) -> dict[str, Any]:
        extra = dict(self.header_extra or {})
        clash = sorted(set(extra) & {"servo_calibration", "payload", "servo_drive", "boresight", "config",
                                     POSE_SOURCE_KEY})
        if clash:
            raise ValueError(f"header extra key {clash[0]!r} would replace one the payload writes")
        return extra

    def effective_config(self) -> dict[str, Any]:
        """What this payload runs with, in the configuration file's sections (`firmware_py.core.config_file`),
        after the command line's flags: the header's ``config`` record, and what `--check` prints. Only
        what the payload itself uses; ``file`` names the configuration file it started from (None: none)."""
        cal = self.servo
        payload: dict[str, Any] = {"rangefinder": self.rangefinder.value}
        if self.rangefinder is Rangefinder.TFMINI:
            payload["uart"] = self.uart_url
        else:
            payload["i2c"] = self.i2c_url
        payload.update({
            "pwm": self.pwm_url, "mavlink": self.mavlink_url,
            "rate_hz": float(self.rate_hz), "log": os.fspath(self.out_path),
            "lever_arm_m": [float(v) for v in self.lever_arm_body_m],
            "boresight_deg": [_deg(self.boresight.tilt_rad), _deg(self.boresight.sweep_yaw_rad)]})
        if self.rangefinder is Rangefinder.LIDARLITE_V3:
            payload["lidarlite_preset"] = self.preset
        if self.stream_url is not None:
            payload["stream"] = self.stream_url
        if self.signing_key_file is not None:
            payload["signing_key"] = os.fspath(self.signing_key_file)
        if self.send_origin is not None:
            payload["ekf_origin"] = [float(v) for v in self.send_origin]
        payload["stop_on_disarm"] = bool(self.stop_on_disarm)
        if self.start_on_arm:
            payload["start_on_arm"] = True
        payload["servo"] = {"center_us": cal.center_us, "us_per_rad": cal.us_per_rad, "min_us": cal.min_us,
                            "max_us": cal.max_us, "slew_rad_s": cal.slew_rad_s, "lag_s": cal.lag_s}
        payload["sweep"] = {"waveform": self.waveform, "peak_rate_rad_s": float(self.servo_peak_rate_rad_s),
                            "phase": self.initial_position}
        site: dict[str, Any] = dict(self.storage.to_dict())
        if self.site is not None:
            site["origin"] = list(self.site.corner.as_tuple())
            site["heading_deg"] = self.site.to_dict()["heading_deg"]
        else:
            site["heading_deg"] = _deg(self.frame.heading_rad)
        return {"file": None if self.config_file is None else os.fspath(self.config_file),
                "site": site, "payload": payload}
