"""Flight-dynamics plant: JSBSim's F450 quadcopter (ships in the `jsbsim` wheel).

The F450 model (1.4 kg, four DJI E305 motors with 9450 props) declares an old config version and
references sensor files the wheel does not ship; JSBSim prints warnings about both on load. They
are harmless for us (we read true states, not its simulated sensors), so loading happens with the
C library's stdout/stderr redirected, keeping the console clean.

The motors are driven through the model's external ESC inputs `fcs/cmd{FR,AL,FL,AR}_ext_nd`,
which its FCS sums straight into `fcs/cmdEsc*_nd` (its own stability loops are left disengaged,
`fcs/ScasEngage` = 0, and its throttle at 0): our autopilot is the only controller.
"""

from __future__ import annotations

import contextlib
import ctypes
import functools
import io
import math
import multiprocessing.util
import os
import shutil
import sys
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import jsbsim

from firmware_py.core.geodesy import GeodeticPoint
from firmware_py.core.site import DEFAULT_SITE
from sitl.vehicle.api import PlantState

FT = 0.3048
LBS_TO_N = 4.4482216
HP_TO_W = 745.699872
GEAR_HEIGHT_M = 0.1524
"""The F450's contact points sit 0.1524 m below its CG; starting lower launches it off the ground."""
ESC_ORDER = ("FR", "AL", "FL", "AR")
"""JSBSim engine order: engine[0] front right, [1] aft left, [2] front left, [3] aft right."""


PAYLOAD_POINTMASS = """  <pointmass name="payload">
    <weight unit="LBS">0.0</weight>
    <location unit="M"><x>0.0</x><y>0.0</y><z>0.0</z></location>
  </pointmass>
</mass_balance>"""


@functools.cache
def _aircraft_dir() -> str:
    """A copy of the wheel's F450 with a payload point mass added (its mass properties are read-only).

    Made once per process in a temporary directory, removed when the process exits (every `fly` and
    `serve` would otherwise leave one in the system's temporary folder); the wheel itself is never modified.
    Removed by multiprocessing's exit finalizer, not only atexit: a process pool's workers (the campaigns'
    `--jobs`) end with os._exit, which skips atexit, and a forked child must not remove its parent's copy,
    which the finalizer's process check prevents.
    """
    src = Path(jsbsim.get_default_root_dir()) / "aircraft" / "F450"
    root = tempfile.mkdtemp(prefix="pilescan-jsbsim-")
    multiprocessing.util.Finalize(None, shutil.rmtree, args=(root,), kwargs={"ignore_errors": True}, exitpriority=0)
    dst = Path(root) / "F450"
    shutil.copytree(src, dst)
    mass = dst / "Mass.xml"
    mass.write_text(mass.read_text().replace("</mass_balance>", PAYLOAD_POINTMASS))
    return str(dst.parent)


_LIBC = ctypes.CDLL(None)


@contextlib.contextmanager
def _quiet_c_output() -> Iterator[None]:
    """Silence what JSBSim prints: at the fd level, and at Python's level too, because its bindings
    send C++ output to Python's sys.stdout when that is not a plain file (pytest, Jupyter)."""
    sys.stdout.flush()
    sys.stderr.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "wb") as null, contextlib.redirect_stdout(io.StringIO()), \
                contextlib.redirect_stderr(io.StringIO()):
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
            _LIBC.fflush(None)  # C++ streams sit on C stdio buffers: flush them while still silenced
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


@dataclass(frozen=True)
class PlantConfig:
    """JSBSim plant settings.

    Attributes:
        dt_s: physics step.
        payload_kg: extra mass at the CG (40 g 1D LiDAR + servo; 370 g 2D; 830 g 3D, paper Sec. 4.5).
        start_ned_m: initial position (NED, down = -height above the floor).
        start_yaw_rad: initial heading.
        airborne: start hovering at start_ned_m (True) or resting on the floor below it (False).
        origin: where on Earth the local NED frame's origin is (the autopilot's EKF origin and home):
            JSBSim flies over the ellipsoid, so it needs a place; the floor is at origin.alt_m.
    """

    dt_s: float = 1.0 / 200.0
    payload_kg: float = 0.040
    start_ned_m: tuple[float, float, float] = (0.0, 0.0, 0.0)
    start_yaw_rad: float = 0.0
    airborne: bool = False
    origin: GeodeticPoint = DEFAULT_SITE.corner

    def __post_init__(self) -> None:
        if not (math.isfinite(self.dt_s) and 1e-4 <= self.dt_s <= 0.02):
            raise ValueError(f"plant step must be 0.1-20 ms, got {self.dt_s * 1e3:g} ms")
        if not (math.isfinite(self.payload_kg) and 0.0 <= self.payload_kg <= 2.0):
            raise ValueError(f"payload mass must be 0-2 kg, got {self.payload_kg}")
        if not all(math.isfinite(v) for v in (*self.start_ned_m, self.start_yaw_rad)):
            raise ValueError("plant start position and heading must be finite")
        if not isinstance(self.origin, GeodeticPoint):
            raise ValueError(f"plant origin must be a GeodeticPoint, got {self.origin!r}")


class JsbsimPlant:
    """The F450 in JSBSim, with local NED state read-out and motor energy integration."""

    def __init__(self, cfg: PlantConfig | None = None) -> None:
        self.cfg = cfg or PlantConfig()
        with _quiet_c_output():
            fdm = jsbsim.FGFDMExec(jsbsim.get_default_root_dir())
            fdm.set_debug_level(0)
            fdm.set_aircraft_path(_aircraft_dir())
            if not fdm.load_model("F450"):
                raise RuntimeError("JSBSim could not load the F450 model shipped with the jsbsim wheel")
        self.fdm = fdm
        fdm.set_dt(self.cfg.dt_s)
        fdm["inertia/pointmass-weight-lbs[0]"] = self.cfg.payload_kg / 0.45359237
        n0, e0, d0 = self.cfg.start_ned_m
        origin = self.cfg.origin
        fdm["ic/lat-geod-deg"] = origin.lat_deg + math.degrees(n0 / self._r_north())
        fdm["ic/long-gc-deg"] = origin.lon_deg + math.degrees(e0 / self._r_east())
        fdm["ic/terrain-elevation-ft"] = origin.alt_m / FT
        height = max(-d0, GEAR_HEIGHT_M + 0.003) if self.cfg.airborne else GEAR_HEIGHT_M + 0.003
        fdm["ic/h-agl-ft"] = height / FT
        fdm["ic/psi-true-deg"] = math.degrees(self.cfg.start_yaw_rad)
        for k in ("u-fps", "v-fps", "w-fps", "p-rad_sec", "q-rad_sec", "r-rad_sec"):
            fdm[f"ic/{k}"] = 0.0
        with _quiet_c_output():
            fdm.run_ic()
        fdm["fcs/ScasEngage"] = 0.0
        fdm["fcs/throttle-cmd-norm"] = 0.0
        for i in range(4):
            fdm[f"propulsion/engine[{i}]/set-running"] = 1
        pm = fdm.get_property_manager()
        node = pm.get_node
        self._esc = [node(f"fcs/cmd{m}_ext_nd") for m in ESC_ORDER]
        self._power = [node(f"propulsion/engine[{i}]/power-hp") for i in range(4)]
        self._get = {name: node(path).get_double_value for name, path in {
            "lat": "position/lat-geod-rad", "lon": "position/long-gc-rad", "h": "position/h-agl-ft",
            "vn": "velocities/v-north-fps", "ve": "velocities/v-east-fps", "vd": "velocities/v-down-fps",
            "phi": "attitude/phi-rad", "theta": "attitude/theta-rad", "psi": "attitude/psi-rad",
            "p": "velocities/p-rad_sec", "q": "velocities/q-rad_sec", "r": "velocities/r-rad_sec",
        }.items()}
        self._lat0 = math.radians(origin.lat_deg)
        self._lon0 = math.radians(origin.lon_deg)
        self.t_s = 0.0
        self.energy_j = 0.0

    @property
    def mass_kg(self) -> float:
        return self.fdm["inertia/mass-slugs"] * 14.5939029

    def _r_north(self) -> float:
        return 6_371_000.0

    def _r_east(self) -> float:
        return 6_371_000.0 * math.cos(math.radians(self.cfg.origin.lat_deg))

    def set_escs(self, fr: float, al: float, fl: float, ar: float) -> None:
        """Motor commands, 0..1 (the model clips them)."""
        for node, v in zip(self._esc, (fr, al, fl, ar), strict=True):
            node.set_double_value(v)

    def step(self) -> None:
        """Advance one physics step and integrate motor power into energy."""
        self.fdm.run()
        self.t_s += self.cfg.dt_s
        self.energy_j += sum(p.get_double_value() for p in self._power) * HP_TO_W * self.cfg.dt_s

    def power_w(self) -> float:
        return sum(p.get_double_value() for p in self._power) * HP_TO_W

    def read(self) -> PlantState:
        """The rigid body's state now (NED metres, m/s, rad, rad/s)."""
        g = self._get
        n = (g["lat"]() - self._lat0) * self._r_north()
        e = math.remainder(g["lon"]() - self._lon0, math.tau) * self._r_east()  # across the antimeridian too
        d = -g["h"]() * FT  # the CG's height above the floor
        return PlantState(n, e, d, g["vn"]() * FT, g["ve"]() * FT, g["vd"]() * FT, g["phi"](), g["theta"](),
                          g["psi"](), g["p"](), g["q"](), g["r"]())
