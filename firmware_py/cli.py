"""`pilescan-payload`: the survey payload on the drone's companion computer (a LIDAR-Lite v3 on I2C or a
TFMini on a UART, on a sweeping servo; poses from the autopilot over MAVLink; a crash-safe sample log).
With --start-on-arm it waits on the ground (servo idle, no log) until the autopilot arms. Stops on
SIGINT/SIGTERM (Ctrl-C), after --duration, or with --stop-on-disarm when the autopilot disarms; the log is
complete either way. --config FILE sets the options from a TOML file (docs/configuration.md);
--check validates and prints the effective configuration without opening any hardware; --preflight opens it,
sweeps and samples for a few seconds without writing a log, and prints a checklist (exit 4 when a check fails).
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import math
import os
import re
import sys
from collections.abc import Callable, Mapping, Sequence
from pathlib import Path
from typing import Any

from firmware_py.app import PROG, PayloadApp
from firmware_py.core.cli import (
    ArgumentParser,
    ConfigTables,
    ExitCode,
    UserError,
    add_config_option,
    add_verbosity,
    finite_float,
    one_line,
    rangefinder_arg,
    reading_input,
    run_cli,
    stop_on_signals,
)
from firmware_py.core.config_file import SECTIONS, ConfigError, parse_config, to_toml
from firmware_py.core.frames import Boresight, StorageFrame
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.keys import load_key
from firmware_py.core.rundir import publish_file
from firmware_py.core.sensor import Rangefinder
from firmware_py.core.servo_model import ServoCalibration
from firmware_py.core.site import Site, add_site_options
from firmware_py.core.storage import Storage
from firmware_py.core.stream_format import parse_stream_url
from firmware_py.core.version import software_version
from firmware_py.core.waveform import N_PHASES
from firmware_py.drivers.lidarlite import PRESETS, preset_by_name
from firmware_py.hal.backends import check_i2c_url
from firmware_py.hal.bridge import parse_tcp_url
from firmware_py.hal.mavlink_link import check_mavlink_url
from firmware_py.hal.pwm import check_pwm_url
from firmware_py.hal.signing import SigningConfig
from firmware_py.hal.uart import check_uart_url
from firmware_py.log_room import check_destination, describe_room, room_s, room_warning
from firmware_py.payload_config import (
    DEFAULT_I2C_URL,
    DEFAULT_MAVLINK_URL,
    DEFAULT_PRESET,
    DEFAULT_PWM_URL,
    DEFAULT_RANGEFINDER,
    DEFAULT_UART_URL,
    PayloadConfig,
)

_HAL_RE = re.compile(r"sitl:(?P<host>[^\s:]+):(?P<port>\d{1,5})")

CONFIG_OPTIONS: ConfigTables = {None: {
    "site.dimensions": "--storage",
    "site.origin": "--origin",
    "site.heading_deg": "--heading",
    "payload.rangefinder": "--rangefinder",
    "payload.i2c": "--i2c",
    "payload.uart": "--uart",
    "payload.pwm": "--pwm",
    "payload.mavlink": "--mavlink",
    "payload.rate_hz": "--rate",
    "payload.log": "--out",
    "payload.lever_arm_m": "--lever-arm",
    "payload.boresight_deg": "--boresight",
    "payload.lidarlite_preset": "--preset",
    "payload.stream": "--stream",
    "payload.signing_key": "--signing-key",
    "payload.ekf_origin": "--send-origin",
    "payload.stop_on_disarm": "--stop-on-disarm",
    "payload.start_on_arm": "--start-on-arm",
    "payload.servo.center_us": "--servo-center-us",
    "payload.servo.us_per_rad": "--servo-us-per-rad",
    "payload.servo.min_us": "--servo-min-us",
    "payload.servo.max_us": "--servo-max-us",
    "payload.servo.slew_rad_s": "--servo-slew-rad-s",
    "payload.servo.lag_s": "--servo-lag-s",
    "payload.sweep.waveform": "--waveform",
    "payload.sweep.peak_rate_rad_s": "--servo-rate",
    "payload.sweep.phase": "--phase",
}}
"""Configuration key -> the option it sets (`firmware_py.core.cli.apply_config`; docs/configuration.md)."""

SERVO_OPTIONS = (("center_us", "--servo-center-us", "US", "pulse width at gamma = 0 (beam straight down), us"),
                 ("us_per_rad", "--servo-us-per-rad", "US", "pulse change per radian (negative: a longer pulse "
                                                           "turns the beam to port), us/rad"),
                 ("min_us", "--servo-min-us", "US", "shortest pulse the servo accepts, us"),
                 ("max_us", "--servo-max-us", "US", "longest pulse the servo accepts, us"),
                 ("slew_rad_s", "--servo-slew-rad-s", "RAD_S", "the servo's top speed, rad/s"),
                 ("lag_s", "--servo-lag-s", "S", "time constant of the servo's position loop, s"))
"""The servo calibration's options: `ServoCalibration` field, option, metavar, help."""


def _checked(check: Callable[[str], object]) -> Callable[[str], str]:
    """argparse type: the text itself, once check(text) accepts it (its ValueError is the message)."""
    def convert(text: str) -> str:
        try:
            check(text)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc).splitlines()[0]) from None
        return text
    return convert


def _positive_seconds(text: str) -> float:
    """argparse type: a duration in seconds, > 0 and at most an hour."""
    v = finite_float(text)
    if not 0.0 < v <= 3600.0:
        raise argparse.ArgumentTypeError(f"must be between 0 and 3600 s, got {text!r}")
    return v


def _check_uart(url: str) -> None:
    if not url.strip():
        raise ValueError("must be a non-empty URL (leave it out for the default)")
    check_uart_url(url)


def _check_i2c(url: str) -> None:
    if not url.strip():
        raise ValueError("must be a non-empty URL (leave it out for the default)")
    check_i2c_url(url)


def _check_pwm(url: str) -> None:
    if not url.strip():
        raise ValueError("must be a non-empty URL (leave it out for the default)")
    check_pwm_url(url)


def _check_preset(name: str) -> None:
    preset_by_name(name)


def hal_urls(hal: str) -> tuple[str, str]:
    """--hal sitl:HOST:PORT -> (I2C URL, PWM URL) of the networked SITL's device bridge."""
    m = _HAL_RE.fullmatch(hal.strip())
    if m is None or not 1 <= int(m.group("port")) <= 65535:
        raise UserError(f"--hal must look like sitl:HOST:PORT (the SITL's device bridge), got {hal!r}")
    host, port = m.group("host"), int(m.group("port"))
    try:
        parse_tcp_url(f"tcp:{host}:{port}")  # the bridge's own check, before anything is opened
    except ValueError:
        raise UserError(f"--hal must look like sitl:HOST:PORT (the SITL's device bridge), got {hal!r}") from None
    return f"tcp:{host}:{port}", f"pwm:tcp:{host}:{port}:0"


def build_parser() -> ArgumentParser:
    ap = ArgumentParser(prog=PROG, description=__doc__)
    ap.add_argument("--version", action="version", version=software_version())
    hw = ap.add_argument_group("hardware (URLs)")
    add_config_option(ap)
    ap.add_argument("--check", action="store_true",
                    help="validate the options (and --config file), print the effective configuration as TOML and "
                         "exit, opening no hardware")
    ap.add_argument("--write-header", type=Path, default=None, metavar="FILE",
                    help="with --check: also write the sample-log header a flight with this configuration starts its "
                         "log with, as JSON (pilescan-ground listen --header FILE: the live log then has the building "
                         "and the sensor's placement)")
    ap.add_argument("--preflight", nargs="?", type=_positive_seconds, const=0.0, default=None, metavar="S",
                    help="check the payload on the ground before a flight: open the hardware, sweep and sample for "
                         "S seconds (at least one sweep period; default: three, and at least 5 s) without writing a "
                         "log, and print a checklist of the autopilot link, pose, EKF sources, rangefinder, loop, "
                         "servo sweep and log card; exit 4 when a check fails, and the ground station is told "
                         "(STATUSTEXT)")
    hw.add_argument("--mavlink", default=DEFAULT_MAVLINK_URL, metavar="URL", type=_checked(check_mavlink_url),
                    help="link to the autopilot: serial:/dev/ttyAMA0:921600, udp:HOST:PORT (listen), "
                         f"udpout:HOST:PORT, tcp:HOST:PORT (default {DEFAULT_MAVLINK_URL})")
    hw.add_argument("--rangefinder", type=rangefinder_arg, default=DEFAULT_RANGEFINDER,
                    metavar="|".join(r.value for r in Rangefinder),
                    help="the rangefinder fitted: lidarlite-v3 (Garmin LIDAR-Lite v3 on --i2c, 500 Hz) or tfmini "
                         "(Benewake TFMini family on --uart, paced by its frames, 100 Hz from the factory) "
                         f"(default {DEFAULT_RANGEFINDER.value})")
    hw.add_argument("--uart", default=None, metavar="URL", type=_checked(_check_uart),
                    help="with --rangefinder tfmini: its serial port, serial:/dev/PATH[:BAUD] (the Pi's header UART "
                         f"is /dev/serial0, a USB adapter /dev/ttyUSB0; default {DEFAULT_UART_URL})")
    hw.add_argument("--i2c", default=None, metavar="URL", type=_checked(_check_i2c),
                    help=f"the LIDAR-Lite's I2C bus: i2c:1, i2c:/dev/i2c-1, tcp:HOST:PORT (default {DEFAULT_I2C_URL})")
    hw.add_argument("--pwm", default=None, metavar="URL", type=_checked(_check_pwm),
                    help="the servo's PWM output: pwm:sysfs:CHIP:CH, pwm:pca9685:BUS:ADDR:CH, pwm:mavlink:N, "
                         f"pwm:tcp:HOST:PORT:CH (default {DEFAULT_PWM_URL})")
    hw.add_argument("--hal", default=None, metavar="sitl:HOST:PORT",
                    help="the networked SITL's device bridge: sets --i2c tcp:HOST:PORT and --pwm pwm:tcp:HOST:PORT:0 "
                         "(with --rangefinder tfmini only the servo: the TFMini is on --uart)")
    out = ap.add_argument_group("output")
    out.add_argument("--out", default=None, metavar="PATH",
                     help="sample log to write (.pslog); {utc} in it becomes the start time (20261124T235301Z); "
                          "required, here or as [payload] log in --config")
    out.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    out.add_argument("--stream", default=None, metavar="URL", type=_checked(parse_stream_url),
                     help="also stream samples live to the ground station: udp:HOST:PORT")
    out.add_argument("--mission-id", default=None, metavar="ID", help="mission id written to the log header")
    add_verbosity(out, quiet_help="no progress lines (warnings and errors still print)")
    sv = ap.add_argument_group("sensor and servo")
    sv.add_argument("--preset", default=DEFAULT_PRESET, metavar="NAME", type=_checked(_check_preset),
                    help=f"LIDAR-Lite preset: {', '.join(PRESETS)} (default {DEFAULT_PRESET})")
    sv.add_argument("--rate", type=finite_float, default=None, metavar="HZ",
                    help="sample rate, Hz (default: the rangefinder's, 500 LIDAR-Lite, 100 TFMini; a TFMini sends "
                         "frames at the rate it is set to, and this says which)")
    sv.add_argument("--waveform", choices=("semi-triangular", "sinusoidal"), default="semi-triangular",
                    help="servo waveform (eq. 1; C=0.95 or C=0)")
    sv.add_argument("--servo-rate", type=finite_float, default=5.0, metavar="RAD_S",
                    help="peak servo rate, rad/s (sets f; default 5 -> 0.67 Hz semi-triangular)")
    sv.add_argument("--phase", type=int, default=0, metavar="K",
                    help=f"servo initial position 0..{2 * N_PHASES - 1} (Fig. 9: {N_PHASES} phases x 2 directions; "
                         f"K >= {N_PHASES} sweeps the other way)")
    sv.add_argument("--lever-arm", type=finite_float, nargs=3, default=(0.0, 0.0, 0.10), metavar=("X", "Y", "Z"),
                    help="sensor position from the centre of gravity, body FRD, m (default 0 0 0.10)")
    sv.add_argument("--boresight", type=finite_float, nargs=2, default=None, metavar=("TILT_DEG", "SWEEP_YAW_DEG"),
                    help="the beam's mounting off square: tilt out of the sweep plane (> 0 leans forward) and yaw of "
                         "the servo axis about body z (> 0 clockwise from above), deg, each within +-45 "
                         "(default 0 0); the ground station places points with it")
    for name, option, metavar, text in SERVO_OPTIONS:
        sv.add_argument(option, type=finite_float, default=None, metavar=metavar,
                        help=f"servo calibration: {text} (default {getattr(ServoCalibration(), name):.6g})")
    sv.add_argument("--storage", default="60x40x15", metavar="LxWxH",
                    help="building inside dimensions in metres, for the log header (default 60x40x15)")
    sec = ap.add_argument_group("link security")
    sec.add_argument("--signing-key", default=None, metavar="FILE",
                     help="MAVLink 2 signing key file: 64 hex digits, or a passphrase line (key = its SHA-256, as "
                          "MAVProxy's 'signing setup'); not readable by others (chmod 600). Signs what we send, "
                          "refuses unsigned, forged and replayed frames, authenticates the --stream datagrams and, "
                          "with --hal or tcp: device URLs, the connection to the SITL's device bridge")
    sec.add_argument("--allow-unsigned", action="store_true",
                     help="with --signing-key: also accept UNSIGNED frames (mixed setups while migrating; "
                          "forged and replayed signed frames are still refused)")
    st = ap.add_argument_group("starting, stopping and the autopilot")
    st.add_argument("--duration", type=finite_float, default=None, metavar="S",
                    help="stop after S seconds of sampling (default: until Ctrl-C / SIGTERM)")
    st.add_argument("--stop-on-disarm", action="store_true",
                    help="stop when the autopilot's HEARTBEAT shows disarmed after having shown armed")
    st.add_argument("--start-on-arm", action="store_true",
                    help="wait, the servo idle and no log open, until the autopilot's HEARTBEAT shows armed, then "
                         "open the log and sweep; stopped before that, no log is written (with --stop-on-disarm "
                         "and a service that restarts the payload: one log per flight)")
    st.add_argument("--send-origin", type=finite_float, nargs=3, default=None, metavar=("LAT", "LON", "ALT"),
                    help="send SET_GPS_GLOBAL_ORIGIN (deg, deg, m MSL) at start: an indoor EKF needs an origin "
                         "before it publishes LOCAL_POSITION_NED (default with --origin: the site's corner)")
    site = ap.add_argument_group("site (the storage frame in the log header)")
    add_site_options(site, default=None)
    return ap


def site_from_cli(args) -> tuple[Site | None, StorageFrame, tuple[float, float, float] | None]:
    """--origin / --heading / --send-origin -> (site, storage frame, EKF origin to send).

    With --origin the site is known: the EKF origin sent is its corner unless --send-origin names another,
    and the frame is the site about that origin. Without it the corner is taken to be the EKF origin
    (whatever sets it), turned by --heading; no site is recorded and nothing is sent unless asked.
    """
    send = tuple(args.send_origin) if args.send_origin is not None else None
    heading_rad = math.radians(args.heading) if args.heading is not None else 0.0
    if args.origin is None:
        return None, StorageFrame(heading_rad=heading_rad), send
    site = Site(args.origin, heading_rad)
    if send is None:
        send = site.corner.as_tuple()
    return site, site.frame_about(GeodeticPoint(*send)), send


def signing_from_args(args) -> SigningConfig | None:
    """--signing-key / --allow-unsigned -> SigningConfig (None without a key); one-line errors."""
    if args.signing_key is None:
        if args.allow_unsigned:
            raise UserError("--allow-unsigned needs --signing-key")
        return None
    with reading_input():
        key = load_key(args.signing_key)
    return SigningConfig(key, allow_unsigned=args.allow_unsigned)


def uses_device_bridge(i2c_url: str, pwm_url: str) -> bool:
    """Whether either URL is the networked SITL's device bridge (the one device link a key authenticates)."""
    return i2c_url.strip().startswith("tcp:") or pwm_url.strip().startswith("pwm:tcp:")


def servo_from_args(args) -> ServoCalibration:
    """The built-in calibration with the --servo-* options given (ValueError naming a bad combination)."""
    given = {name: getattr(args, option[2:].replace("-", "_"), None) for name, option, _, _ in SERVO_OPTIONS}
    return ServoCalibration(**{k: v for k, v in given.items() if v is not None})


def boresight_from_args(args) -> Boresight:
    if args.boresight is None:
        return Boresight()
    tilt, yaw = args.boresight
    if abs(tilt) > 45.0 or abs(yaw) > 45.0:
        raise UserError(f"--boresight angles must be within +-45 deg, got {tilt:g} {yaw:g}")
    return Boresight(math.radians(tilt), math.radians(yaw))


UTC_FIELD = "{utc}"
"""In --out (or [payload] log), replaced by the start time: one configuration file, a new log each flight."""


def expand_log_name(path: str, now: dt.datetime | None = None) -> str:
    """path with each {utc} replaced by the UTC time as 20261124T235301Z (sorts, and is a valid file name
    on every system)."""
    stamp = (now or dt.datetime.now(dt.UTC)).strftime("%Y%m%dT%H%M%SZ")
    return path.replace(UTC_FIELD, stamp)


URL_KEYS = ("i2c", "pwm", "uart", "mavlink", "stream")
"""The effective configuration's part URLs: checked by their registries, not by the file schema's URL form."""


def config_from_args(args) -> PayloadConfig:
    """PayloadConfig from parsed options (ValueError / UserError for bad values, one line each)."""
    if args.out is None:
        raise UserError("--out is required (the sample log to write; or [payload] log in the --config file)")
    out = expand_log_name(args.out)
    signing = signing_from_args(args)
    from_file = getattr(args, "config_keys", {})
    i2c_flag = args.i2c if "i2c" not in from_file else None
    pwm_flag = args.pwm if "pwm" not in from_file else None
    uart_flag = args.uart if "uart" not in from_file else None
    preset_flag = args.preset if "lidarlite_preset" not in from_file else DEFAULT_PRESET
    i2c, pwm = args.i2c or DEFAULT_I2C_URL, args.pwm or DEFAULT_PWM_URL
    if args.hal is not None:  # the command line's --hal overrides the file's buses, as any flag does
        if i2c_flag is not None or pwm_flag is not None:
            raise UserError("--hal sets --i2c and --pwm: give either --hal or those two")
        i2c, pwm = hal_urls(args.hal)
    # A configuration file may name both sensors' ports (the rig's wiring); a flag for the sensor not fitted is
    # a mistake worth a line.
    tfmini = args.rangefinder is Rangefinder.TFMINI
    if uart_flag is not None and not tfmini:
        raise UserError("--uart is the TFMini's serial port: give it with --rangefinder tfmini")
    if tfmini and i2c_flag is not None:
        raise UserError("--i2c is the LIDAR-Lite's bus: a TFMini is on --uart")
    if tfmini and preset_flag != DEFAULT_PRESET:
        raise UserError("--preset is the LIDAR-Lite's: a TFMini has none")
    device_key = signing.key if signing is not None and uses_device_bridge(i2c if not tfmini else "", pwm) else None
    site, frame, send_origin = site_from_cli(args)
    cfg = PayloadConfig(
        out_path=out, force=args.force, mavlink_url=args.mavlink, rangefinder=args.rangefinder,
        uart_url=args.uart or DEFAULT_UART_URL, i2c_url=i2c, pwm_url=pwm,
        preset=args.preset, rate_hz=args.rate, waveform=args.waveform, servo_peak_rate_rad_s=args.servo_rate,
        initial_position=args.phase, storage=Storage.parse(args.storage), servo=servo_from_args(args),
        site=site, frame=frame,
        lever_arm_body_m=tuple(args.lever_arm), boresight=boresight_from_args(args), duration_s=args.duration,
        stop_on_disarm=args.stop_on_disarm, start_on_arm=args.start_on_arm, stream_url=args.stream,
        send_origin=send_origin,
        mission_id=args.mission_id, quiet=args.quiet, signing=signing, device_key=device_key,
        config_file=args.config, signing_key_file=args.signing_key)
    # The flags' values must be what a configuration file may hold: --check prints this as one, the log's header
    # carries it, and a flag past the schema's range (a lever arm of 1e9 m) would fly as given.
    eff = cfg.effective_config()
    eff.pop("file")
    for key in URL_KEYS:  # checked above against this process's registries, which may know more schemes (sitl)
        eff["payload"].pop(key, None)
    try:
        parse_config(eff, source="the command line" if args.config is None
                     else f"{args.config} with the command line's flags")
    except ConfigError as exc:
        raise UserError(str(exc)) from None
    return cfg


def _merged(file: Mapping[str, Any], over: Mapping[str, Any]) -> dict[str, Any]:
    """The file's sections and keys with over's put over them, table by table (over's keys first, in its order)."""
    out = dict(over)
    for key, value in file.items():
        if key not in out:
            out[key] = value
        elif isinstance(value, Mapping) and isinstance(out[key], Mapping):
            out[key] = _merged(value, out[key])
    return out


def printed_config(cfg: PayloadConfig, args: argparse.Namespace) -> dict[str, Any]:
    """The configuration --check prints, as sections: what the payload runs with (the effective configuration,
    flags over the file over the built-in defaults) over the --config file's own keys, so that the sections and keys
    the payload does not use ([mission], [sitl], [survey], [[piles]], [site] name, the other rangefinder's port) are
    kept, and the log path as written, its {utc} not yet the start time: printed, saved and read again, it is the
    same configuration, and a new log each flight."""
    eff = cfg.effective_config()
    eff.pop("file")
    payload = eff["payload"]
    payload["log"] = os.path.abspath(os.path.expanduser(args.out))  # a file's paths are its folder's, not ours
    if "signing_key" in payload:
        payload["signing_key"] = os.path.abspath(os.path.expanduser(payload["signing_key"]))
    file = getattr(args, "config_file", None)
    return _merged(file.to_dict() if file is not None else {}, eff)


def check_text(cfg: PayloadConfig, args: argparse.Namespace) -> str:
    """What --check prints: `printed_config` as TOML (it reads back as a configuration file), after comments saying
    where it came from and what a {utc} in the log path becomes."""
    printed = printed_config(cfg, args)
    head = (f"# effective configuration of {PROG}: {args.config} with the command line's flags over it\n"
            if args.config is not None
            else f"# effective configuration of {PROG} (no --config file: flags and built-in defaults)\n")
    if UTC_FIELD in printed["payload"]["log"]:
        head += (f"# [payload] log: {UTC_FIELD} becomes the start time of each flight; started now, "
                 f"{cfg.out_path}\n")
    return head + to_toml({name: printed[name] for name in SECTIONS if name in printed})


def write_header_json(cfg: PayloadConfig, path: Path) -> Path:
    """--check --write-header: the header this configuration's log would start with, as a JSON object (what
    `pilescan-ground listen --header` reads), written whole or not at all. Not the flight's own: no servo drive
    start and no autopilot parameters, which only a flight knows, and the ground station needs neither to place
    points."""
    text = json.dumps(cfg.log_header(), indent=2, default=str) + "\n"
    tmp = path.with_name(path.name + ".tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        return publish_file(tmp, path, force=True)  # a header is derived: a newer one replaces it
    except OSError as exc:
        tmp.unlink(missing_ok=True)
        raise UserError(f"--write-header {path}: {one_line(exc)}") from exc


def log_notes(cfg: PayloadConfig) -> tuple[str | None, list[str]]:
    """What --check says of the log, as the payload would open it on this machine: a TOML comment with the room its
    file system holds, and warnings: why it could not be written, or that the room is less than the flight
    (warnings, not errors: a configuration checked on another machine than the one it is for names that machine's
    paths)."""
    out = Path(cfg.out_path)
    try:
        check_destination(out, cfg.force)
    except UserError as exc:
        return None, [f"{exc} (on this machine)"]
    room = room_s(out, cfg.rate_hz, cfg.records_per_block)
    low = room_warning(room, cfg.duration_s, cfg.rate_hz)
    note = None if room is None else (f"# the log's file system has room for {describe_room(room)} of samples at "
                                      f"{cfg.rate_hz:g} Hz\n")
    return note, [low] if low else []


def _run(args) -> int:
    cfg = config_from_args(args)
    if args.check and args.preflight is not None:
        raise UserError("--check opens no hardware and --preflight opens it: give one of them")
    if args.write_header is not None and not args.check:
        raise UserError("--write-header goes with --check (it writes what a flight's log would start with)")
    if args.check:
        note, warnings = log_notes(cfg)
        print(check_text(cfg, args) + (note or ""), end="")
        if args.write_header is not None:
            write_header_json(cfg, args.write_header)
        for w in warnings:
            print(f"{PROG}: warning: {w}", file=sys.stderr)
        return 0
    if args.preflight is not None:
        return _preflight(cfg, args.preflight or None)
    app = PayloadApp(cfg, err=sys.stderr)
    with stop_on_signals(app.request_stop):
        app.run()
    return 0


def _preflight(cfg: PayloadConfig, duration_s: float | None) -> int:
    """--preflight: the checklist on standard output; exit 4 when a check failed."""
    app = PayloadApp(cfg, err=sys.stderr)
    with stop_on_signals(app.request_stop):
        result = app.preflight(duration_s)
    print("\n".join(result.lines()))
    return ExitCode.OK if result.passed else ExitCode.RUNTIME


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _run, config=CONFIG_OPTIONS)


if __name__ == "__main__":
    raise SystemExit(main())
