"""PWM outputs for the servo: Linux sysfs PWM, a PCA9685 on the I2C bus, or the autopilot's servo
output through MAVLink (MAV_CMD_DO_SET_SERVO). Chosen by URL:

    pwm:sysfs:CHIP:CHANNEL            /sys/class/pwm/pwmchipCHIP/pwmCHANNEL
    pwm:pca9685:I2C_BUS:ADDR:CHANNEL  e.g. pwm:pca9685:1:0x40:0
    pwm:mavlink:SERVO_N               the autopilot's SERVOn output (needs the MAVLink link)
    pwm:tcp:HOST:PORT:CHANNEL         a SITL PWM output (its emulated servo) over the networked-SITL
                                      device bridge (firmware_py.hal.bridge)

`open_pwm(url, key=...)`: the key authenticates the device bridge; the other outputs ignore it.
The schemes live in `PWM_BACKENDS`, a `firmware_py.hal.registry.BackendRegistry` (the rules every
URL-selected backend follows); another layer adds its own with `register_pwm_backend`.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

from firmware_py.hal import I2CBus, MavlinkLink, PwmOutput, check_i2c_addr, check_pulse_us
from firmware_py.hal.registry import BackendRegistry

FRAME_HZ = 50.0


class SysfsPwm:
    """A Linux PWM channel through /sys/class/pwm (e.g. the Raspberry Pi's hardware PWM)."""

    def __init__(self, chip: int, channel: int, frame_hz: float = FRAME_HZ, root: str | Path = "/sys/class/pwm"):
        self.dir = Path(root) / f"pwmchip{chip}"
        if not self.dir.is_dir():
            raise OSError(f"no PWM chip at {self.dir} (enable the PWM overlay, e.g. dtoverlay=pwm)")
        self.ch = self.dir / f"pwm{channel}"
        if not self.ch.is_dir():
            (self.dir / "export").write_text(str(channel))
        self.period_ns = round(1e9 / frame_hz)
        (self.ch / "period").write_text(str(self.period_ns))
        (self.ch / "enable").write_text("1")

    def set_pulse_us(self, pulse_us: float) -> None:
        (self.ch / "duty_cycle").write_text(str(round(check_pulse_us(pulse_us) * 1000)))

    def disable(self) -> None:
        (self.ch / "enable").write_text("0")

    def close(self) -> None:
        self.disable()


class Pca9685Pwm:
    """One channel of a PCA9685 16-channel PWM driver (I2C, 25 MHz oscillator, 12-bit)."""

    _MODE1, _PRESCALE, _LED0_ON_L = 0x00, 0xFE, 0x06
    _SLEEP, _AI, _RESTART = 0x10, 0x20, 0x80
    OSC_HZ = 25_000_000

    def __init__(self, bus: I2CBus, addr: int = 0x40, channel: int = 0, frame_hz: float = FRAME_HZ,
                 sleep: Callable[[float], None] | None = None) -> None:
        if not (0 <= channel <= 15):
            raise ValueError(f"PCA9685 channel must be 0-15, got {channel}")
        check_i2c_addr(addr)
        self.bus, self.addr, self.channel = bus, addr, channel
        self.frame_hz = frame_hz
        self.prescale = prescale_for(frame_hz)
        # Sleep to set the prescaler, wake with auto-increment, restart (datasheet sec. 7.3.1.1).
        bus.write(addr, bytes([self._MODE1, self._SLEEP | self._AI]))
        bus.write(addr, bytes([self._PRESCALE, self.prescale]))
        bus.write(addr, bytes([self._MODE1, self._AI]))
        if sleep is not None:
            sleep(0.0005)  # oscillator start-up, 500 us
        bus.write(addr, bytes([self._MODE1, self._AI | self._RESTART]))

    @property
    def actual_frame_hz(self) -> float:
        return self.OSC_HZ / (4096 * (self.prescale + 1))

    def set_pulse_us(self, pulse_us: float) -> None:
        ticks = round(check_pulse_us(pulse_us) * 1e-6 * self.actual_frame_hz * 4096)
        reg = self._LED0_ON_L + 4 * self.channel
        self.bus.write(self.addr, bytes([reg, 0, 0, ticks & 0xFF, ticks >> 8]))

    def disable(self) -> None:
        reg = self._LED0_ON_L + 4 * self.channel
        self.bus.write(self.addr, bytes([reg, 0, 0, 0, 0x10]))  # full OFF bit

    def close(self) -> None:
        self.disable()


def prescale_for(frame_hz: float) -> int:
    """PCA9685 prescaler: round(25 MHz / (4096 f)) - 1 (121 at 50 Hz)."""
    if not (math.isfinite(frame_hz) and 24 <= frame_hz <= 1526):
        raise ValueError(f"PCA9685 frame rate must be 24-1526 Hz, got {frame_hz}")
    return round(Pca9685Pwm.OSC_HZ / (4096 * frame_hz)) - 1


class MavlinkServoPwm:
    """The servo on an autopilot output, commanded with MAV_CMD_DO_SET_SERVO (one per PWM frame)."""

    MAV_CMD_DO_SET_SERVO = 183

    def __init__(self, link: MavlinkLink, servo_n: int, mav: Any, target_system: int = 1,
                 target_component: int = 1) -> None:
        if not (1 <= servo_n <= 32):
            raise ValueError(f"autopilot servo output must be 1-32, got {servo_n}")
        self.link, self.servo_n, self.mav = link, servo_n, mav
        self.target = (target_system, target_component)

    def set_pulse_us(self, pulse_us: float) -> None:
        p = round(check_pulse_us(pulse_us))
        self.link.send(self.mav.command_long_encode(*self.target, self.MAV_CMD_DO_SET_SERVO, 0, self.servo_n, p,
                                                    0, 0, 0, 0, 0))

    def disable(self) -> None:
        self.link.send(self.mav.command_long_encode(*self.target, self.MAV_CMD_DO_SET_SERVO, 0, self.servo_n, 0,
                                                    0, 0, 0, 0, 0))

    def close(self) -> None:
        self.disable()


_FORMS = "pwm:sysfs:CHIP:CH, pwm:pca9685:BUS:ADDR:CH (CH 0-15), pwm:mavlink:N or pwm:tcp:HOST:PORT:CH"
_SHAPE = re.compile(r"pwm:([a-z][a-z0-9+.-]*)(?::(.*))?", re.ASCII)


def _fields(url: str, n: int) -> list[str]:
    """The n colon-separated fields after `pwm:SCHEME:`, or ValueError saying what was expected."""
    parts = url.split(":")[2:]
    if len(parts) != n:
        raise ValueError(f"expected {_FORMS}")
    return parts


def _digits(text: str) -> bool:
    return text.isascii() and text.isdigit()


def _named(fn: Callable[..., Any]) -> Callable[..., Any]:
    """A built-in's ValueError, prefixed with the URL it was given (int() messages do not name it)."""
    def wrapper(url: str, *args: Any, **kwargs: Any) -> Any:
        try:
            return fn(url, *args, **kwargs)
        except ValueError as exc:
            raise ValueError(f"bad PWM output {url!r}: {exc}") from None
    return wrapper


def _sysfs_fields(url: str) -> tuple[int, int]:
    chip, channel = _fields(url, 2)
    if not (_digits(chip) and _digits(channel)):
        raise ValueError(f"expected {_FORMS}")
    return int(chip), int(channel)


@_named
def _check_sysfs(url: str) -> None:
    _sysfs_fields(url)


@_named
def _check_pca9685(url: str) -> None:
    bus, addr, channel = _fields(url, 3)
    check_i2c_addr(int(addr, 0))
    if not (_digits(bus) and _digits(channel) and int(channel) < 16):
        raise ValueError(f"expected {_FORMS}")


@_named
def _check_mavlink(url: str) -> None:
    (servo_n,) = _fields(url, 1)
    if not (_digits(servo_n) and 1 <= int(servo_n) <= 32):
        raise ValueError(f"expected {_FORMS} (N 1-32)")


def _check_bridge(url: str) -> None:
    from firmware_py.hal.bridge import parse_pwm_url
    try:
        parse_pwm_url(url)
    except ValueError as exc:
        raise ValueError(f"bad PWM output {url!r}: {exc}") from None


@_named
def _open_sysfs(url: str, **_options: Any) -> PwmOutput:
    return SysfsPwm(*_sysfs_fields(url))


@_named
def _open_pca9685(url: str, *, i2c_opener: Callable[[str], I2CBus] | None = None, **_options: Any) -> PwmOutput:
    bus_n, addr_s, channel_s = _fields(url, 3)
    if i2c_opener is None:
        raise ValueError("a PCA9685 output needs an I2C bus")
    if not (_digits(bus_n) and _digits(channel_s)):
        raise ValueError(f"expected {_FORMS}")
    addr, channel = check_i2c_addr(int(addr_s, 0)), int(channel_s)  # before the bus is opened
    bus = i2c_opener(f"i2c:{bus_n}")
    try:
        return Pca9685Pwm(bus, addr, channel)
    except BaseException:
        bus.close()
        raise


@_named
def _open_mavlink(url: str, *, link: MavlinkLink | None = None, mav: Any = None, **_options: Any) -> PwmOutput:
    (servo_n,) = _fields(url, 1)
    if not _digits(servo_n):
        raise ValueError(f"expected {_FORMS}")
    if link is None or mav is None:
        raise ValueError("a MAVLink servo output needs the autopilot link")
    return MavlinkServoPwm(link, int(servo_n), mav)


def _open_bridge(url: str, key: bytes | None = None, **_options: Any) -> PwmOutput:
    """The device bridge, imported on first use (only a networked SITL run needs its sockets)."""
    from firmware_py.hal.bridge import open_bridge_pwm
    return open_bridge_pwm(url, key=key)


PWM_BACKENDS: BackendRegistry[PwmOutput] = BackendRegistry(
    "PWM output", prefix="pwm:", credential="key", unknown="bad PWM output {url!r}: unknown scheme {scheme!r}",
    expected=_FORMS)
"""Every `open_pwm` scheme (`pwm:SCHEME:...`): the built-in outputs and what other layers register."""
PWM_BACKENDS.builtin("sysfs", _open_sysfs, check=_check_sysfs)
PWM_BACKENDS.builtin("pca9685", _open_pca9685, check=_check_pca9685)
PWM_BACKENDS.builtin("mavlink", _open_mavlink, check=_check_mavlink)
PWM_BACKENDS.builtin("tcp", _open_bridge, takes_credential=True, check=_check_bridge)


def register_pwm_backend(scheme: str, factory: Callable[[str], PwmOutput]) -> None:
    """Let another layer (the SITL) provide `pwm:SCHEME:...` outputs without firmware_py importing it
    (re-registering replaces; the built-in schemes cannot be replaced)."""
    PWM_BACKENDS.register(scheme, factory)


def unregister_pwm_backend(scheme: str) -> None:
    """Forget a registered scheme; unknown schemes are ignored."""
    PWM_BACKENDS.unregister(scheme)


def _check_shape(url: object) -> str:
    if not isinstance(url, str) or not _SHAPE.fullmatch(url.strip()):
        raise ValueError(f"PWM output must look like pwm:sysfs:0:0, pwm:pca9685:1:0x40:0 or pwm:mavlink:9, got {url!r}")
    return url.strip()


def check_pwm_url(url: str) -> None:
    """Refuse a malformed PWM URL without opening anything (ValueError naming it), so a program can
    check all its options before it touches the hardware. Registered schemes are checked when opened."""
    PWM_BACKENDS.check(_check_shape(url))


def open_pwm(url: str, i2c_opener: Callable[[str], I2CBus] | None = None, link: MavlinkLink | None = None,
             mav: Any = None, *, key: bytes | None = None) -> PwmOutput:
    """A PwmOutput from its URL (see the module docstring); `key` authenticates the device bridge
    (`pwm:tcp:`) and is ignored by the local outputs."""
    return PWM_BACKENDS.open(_check_shape(url), key, i2c_opener=i2c_opener, link=link, mav=mav)
