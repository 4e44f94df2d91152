"""A survey flown at a real site, with the building turned: the same survey as at the default site.

Pile 1 at P_traj 20 % in the small building (30 x 20 x 10 m, flown at 9 m: what is tested is the turn, not the
size), the payload firmware in the loop on the JSBSim plant (`pilescan-sitl fly`), once at
the default site (53.4668 N, 2.2339 W, 50 m; x axis north) and once at -33.9, 151.2, 30 m with the x axis
30 deg east of north. The world and the ray tracing are in the building's frame W, the vehicle flies in
NED about the site's corner: the flight is the same flight turned, so it must measure the same volume,
fly the same path in W, and every geodetic message on the link must agree with the site.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from pymavlink import mavutil
from scipy.spatial import cKDTree

from firmware_py.core.frames import StorageFrame
from firmware_py.core.rundir import SAMPLES_FILE, TLOG_FILE, TRUTH_FILE
from firmware_py.core.samplelog import read_samplelog
from firmware_py.core.site import DEFAULT_SITE, Site
from firmware_py.core.surface_file import SURFACE_FILE
from ground.report import ReportOptions, make_report
from ground.surface_file import load_surface
from sitl.cli import main

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)

SYDNEY = Site.of(-33.9, 151.2, 30.0, 30.0)
RUNS = {"default": [], "sydney": ["--origin", "-33.9,151.2,30", "--heading", "30"]}


@pytest.fixture(scope="module")
def flights(tmp_path_factory):
    """Both flights and their reports (the report's dict and its folder), by name."""
    root = tmp_path_factory.mktemp("sites")
    out = {}
    for name, site_args in RUNS.items():
        run = root / name
        assert main(["fly", "--stockpile", "1", "--p-traj", "20", "--storage", "30x20x10", "--altitude", "9",
                     *site_args, "--out", str(run), "-q"]) == 0
        report = root / f"{name}-report"
        out[name] = (run, make_report(run, report, ReportOptions(plots=False)), report)
    return out


def path_w(run) -> np.ndarray:
    """The logged vehicle positions, in the building's frame by the log header's own frame."""
    log = read_samplelog(run / SAMPLES_FILE)
    s = log.samples
    p = StorageFrame.from_dict(log.header["storage_frame"]).ned_to_w(np.column_stack([s["x_m"], s["y_m"], s["z_m"]]))
    return p[np.isfinite(p).all(axis=1)]


def surveyed(report_dir):
    """The surface a report measured (its grid of heights, and which cells were fitted to points rather than filled),
    as the report saved it: the same survey, not computed a second time."""
    return load_surface(report_dir / SURFACE_FILE)


def test_that_the_turned_building_at_another_site_measures_the_same_volume(flights):
    """The same volume, and where both flights saw the pile the same surface, to 0.1 %."""
    assert flights["default"][1]["true_volume_m3"] == flights["sydney"][1]["true_volume_m3"]
    v_default, v_sydney = (flights[k][1]["volume_m3"] for k in ("default", "sydney"))
    assert abs(v_sydney - v_default) / v_default < 0.001
    a, b = surveyed(flights["default"][2]), surveyed(flights["sydney"][2])
    seen = a.fitted & b.fitted
    v_a, v_b = (float(s.heights_m[seen].sum()) * a.grid.cell_m ** 2 for s in (a, b))
    assert abs(v_b - v_a) / v_a < 0.001


def test_that_the_mission_is_flown_along_the_turned_building(flights):
    """In W the two flights' paths coincide; a frame off by the heading would put them metres apart."""
    default, sydney = path_w(flights["default"][0]), path_w(flights["sydney"][0])
    gap_m, _ = cKDTree(default).query(sydney)
    assert gap_m.max() < 0.1
    ned = read_samplelog(flights["sydney"][0] / SAMPLES_FILE).samples
    course = np.degrees(np.arctan2(np.diff(ned["y_m"]), np.diff(ned["x_m"])))
    moving = np.hypot(np.diff(ned["x_m"]), np.diff(ned["y_m"])) > 1e-3  # ~1 m/s at 500 Hz: 2 mm a sample
    first_leg = course[moving][: moving.sum() // 8]  # W0 -> W1, along the building's x axis
    assert np.median(first_leg) == pytest.approx(30.0, abs=1.0)


def test_that_truth_header_and_report_carry_the_site(flights):
    run, report, _ = flights["sydney"]
    truth = json.loads((run / TRUTH_FILE).read_text())
    assert truth["site"] == SYDNEY.to_dict() and truth["ekf_origin"] == {"lat_deg": -33.9, "lon_deg": 151.2,
                                                                          "alt_m": 30.0}
    header = read_samplelog(run / SAMPLES_FILE).header
    assert header["site"] == SYDNEY.to_dict()
    assert header["storage_frame"] == {"origin_ned_m": [0.0, 0.0, 0.0], "heading_rad": math.radians(30.0)}
    assert report["site"] == SYDNEY.to_dict()
    assert flights["default"][1]["site"] == DEFAULT_SITE.to_dict()


def test_that_every_geodetic_message_on_the_link_agrees_with_the_site(flights):
    """The payload's SET_GPS_GLOBAL_ORIGIN is the site's corner, the autopilot confirms it (GPS_GLOBAL_ORIGIN)
    and refuses nothing, and GLOBAL_POSITION_INT, taken back about the corner, is LOCAL_POSITION_NED to
    MAVLink's resolution (1e-7 deg: 1.1 cm; mm in altitude)."""
    run, _, _ = flights["sydney"]
    tlog = mavutil.mavlink_connection(str(run / TLOG_FILE), dialect="ardupilotmega")
    corner = (round(-33.9e7), round(151.2e7), 30_000)
    sent, confirmed, refusals, local, pairs = [], [], [], {}, []
    while (m := tlog.recv_match(type=["SET_GPS_GLOBAL_ORIGIN", "GPS_GLOBAL_ORIGIN", "STATUSTEXT",
                                      "LOCAL_POSITION_NED", "GLOBAL_POSITION_INT"])) is not None:
        kind = m.get_type()
        if kind == "SET_GPS_GLOBAL_ORIGIN":
            sent.append((m.latitude, m.longitude, m.altitude))
        elif kind == "GPS_GLOBAL_ORIGIN":
            confirmed.append((m.latitude, m.longitude, m.altitude))
        elif kind == "STATUSTEXT" and "origin" in m.text.lower():
            refusals.append(m.text)
        elif kind == "LOCAL_POSITION_NED":
            local[m.time_boot_ms] = (m.x, m.y, m.z)
        elif kind == "GLOBAL_POSITION_INT" and m.time_boot_ms in local:
            pairs.append((m, local[m.time_boot_ms]))
    assert sent and set(sent) == {corner} and confirmed and set(confirmed) == {corner} and refusals == []
    assert len(pairs) > 100
    for g, (n, e, d) in pairs:
        gn, ge = SYDNEY.corner.to_ned(g.lat / 1e7, g.lon / 1e7)
        assert math.hypot(gn - n, ge - e) < 0.02
        assert g.alt / 1e3 == pytest.approx(SYDNEY.corner.alt_m - d, abs=2e-3)
        assert g.relative_alt / 1e3 == pytest.approx(-d, abs=2e-3)
