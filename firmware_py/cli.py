"""`pilescan-payload`: the survey payload on the drone's companion computer (LIDAR-Lite on a sweeping servo,
poses from the autopilot over MAVLink, a crash-safe sample log). Stops on SIGINT/SIGTERM (Ctrl-C), after
--duration, or with --stop-on-disarm when the autopilot disarms; the log is complete either way.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Sequence

from firmware_py.app import (
    DEFAULT_I2C_URL,
    DEFAULT_MAVLINK_URL,
    DEFAULT_PRESET,
    DEFAULT_PWM_URL,
    PROG,
    PayloadApp,
    PayloadConfig,
)
from firmware_py.core.cli import (
    ArgumentParser,
    UserError,
    add_verbosity,
    finite_float,
    reading_input,
    run_cli,
    stop_on_signals,
)
from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.keys import load_key
from firmware_py.core.site import Site, add_site_options
from firmware_py.core.storage import Storage
from firmware_py.core.version import software_version
from firmware_py.core.waveform import N_PHASES
from firmware_py.drivers.lidarlite import PRESETS
from firmware_py.hal.bridge import parse_tcp_url
from firmware_py.hal.signing import SigningConfig

_HAL_RE = re.compile(r"sitl:(?P<host>[^\s:]+):(?P<port>\d{1,5})")


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
    hw.add_argument("--mavlink", default=DEFAULT_MAVLINK_URL, metavar="URL",
                    help="link to the autopilot: serial:/dev/ttyAMA0:921600, udp:HOST:PORT (listen), "
                         f"udpout:HOST:PORT, tcp:HOST:PORT (default {DEFAULT_MAVLINK_URL})")
    hw.add_argument("--i2c", default=None, metavar="URL",
                    help=f"the LIDAR-Lite's I2C bus: i2c:1, i2c:/dev/i2c-1, tcp:HOST:PORT (default {DEFAULT_I2C_URL})")
    hw.add_argument("--pwm", default=None, metavar="URL",
                    help="the servo's PWM output: pwm:sysfs:CHIP:CH, pwm:pca9685:BUS:ADDR:CH, pwm:mavlink:N, "
                         f"pwm:tcp:HOST:PORT:CH (default {DEFAULT_PWM_URL})")
    hw.add_argument("--hal", default=None, metavar="sitl:HOST:PORT",
                    help="the networked SITL's device bridge: sets --i2c tcp:HOST:PORT and --pwm pwm:tcp:HOST:PORT:0")
    out = ap.add_argument_group("output")
    out.add_argument("--out", required=True, metavar="PATH", help="sample log to write (.pslog)")
    out.add_argument("--force", action="store_true", help="overwrite --out if it exists")
    out.add_argument("--stream", default=None, metavar="URL",
                     help="also stream samples live to the ground station: udp:HOST:PORT")
    out.add_argument("--mission-id", default=None, metavar="ID", help="mission id written to the log header")
    add_verbosity(out, quiet_help="no progress lines (warnings and errors still print)")
    sv = ap.add_argument_group("sensor and servo")
    sv.add_argument("--preset", default=DEFAULT_PRESET, metavar="NAME",
                    help=f"LIDAR-Lite preset: {', '.join(PRESETS)} (default {DEFAULT_PRESET})")
    sv.add_argument("--rate", type=finite_float, default=500.0, metavar="HZ", help="sample rate, Hz (default 500)")
    sv.add_argument("--waveform", choices=("semi-triangular", "sinusoidal"), default="semi-triangular",
                    help="servo waveform (eq. 1; C=0.95 or C=0)")
    sv.add_argument("--servo-rate", type=finite_float, default=5.0, metavar="RAD_S",
                    help="peak servo rate, rad/s (sets f; default 5 -> 0.67 Hz semi-triangular)")
    sv.add_argument("--phase", type=int, default=0, metavar="K",
                    help=f"servo initial position 0..{2 * N_PHASES - 1} (Fig. 9: {N_PHASES} phases x 2 directions; "
                         f"K >= {N_PHASES} sweeps the other way)")
    sv.add_argument("--lever-arm", type=finite_float, nargs=3, default=(0.0, 0.0, 0.10), metavar=("X", "Y", "Z"),
                    help="sensor position from the centre of gravity, body FRD, m (default 0 0 0.10)")
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
    st = ap.add_argument_group("stopping and the autopilot")
    st.add_argument("--duration", type=finite_float, default=None, metavar="S",
                    help="stop after S seconds (default: until Ctrl-C / SIGTERM)")
    st.add_argument("--stop-on-disarm", action="store_true",
                    help="stop when the autopilot's HEARTBEAT shows disarmed after having shown armed")
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


def config_from_args(args) -> PayloadConfig:
    """PayloadConfig from parsed options (ValueError / UserError for bad values, one line each)."""
    signing = signing_from_args(args)
    for opt, value in (("--i2c", args.i2c), ("--pwm", args.pwm)):
        if value is not None and not value.strip():
            raise UserError(f"{opt} must be a non-empty URL (leave it out for the default)")
    i2c, pwm = args.i2c or DEFAULT_I2C_URL, args.pwm or DEFAULT_PWM_URL
    if args.hal is not None:
        if args.i2c is not None or args.pwm is not None:
            raise UserError("--hal sets --i2c and --pwm: give either --hal or those two")
        i2c, pwm = hal_urls(args.hal)
    device_key = signing.key if signing is not None and uses_device_bridge(i2c, pwm) else None
    site, frame, send_origin = site_from_cli(args)
    return PayloadConfig(
        out_path=args.out, force=args.force, mavlink_url=args.mavlink, i2c_url=i2c, pwm_url=pwm,
        preset=args.preset, rate_hz=args.rate, waveform=args.waveform, servo_peak_rate_rad_s=args.servo_rate,
        initial_position=args.phase, storage=Storage.parse(args.storage), site=site, frame=frame,
        lever_arm_body_m=tuple(args.lever_arm), duration_s=args.duration, stop_on_disarm=args.stop_on_disarm,
        stream_url=args.stream, send_origin=send_origin,
        mission_id=args.mission_id, quiet=args.quiet, signing=signing, device_key=device_key)


def _run(args) -> int:
    cfg = config_from_args(args)
    app = PayloadApp(cfg, err=sys.stderr)
    with stop_on_signals(app.request_stop):
        app.run()
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    return run_cli(build_parser(), argv, _run)


if __name__ == "__main__":
    raise SystemExit(main())
