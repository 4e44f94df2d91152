"""The exported plan: a valid QGC WPL 110 file whose positions are the survey's, flyable over MAVLink."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.frames import StorageFrame
from firmware_py.core.geodesy import global_to_ned
from sitl.cli import main
from sitl.missions.qgc_wpl import DEFAULT_ORIGIN, read_qgc_wpl, write_qgc_wpl
from sitl.missions.rectangle import Mission
from sitl.runners.flight import start_pose
from sitl.vehicle.api import FlightMode
from sitl.vehicle.jsbsim_plant import PlantConfig
from sitl.vehicle.jsbsim_vehicle import JsbsimVehicle, VehicleConfig
from tests.sitl.mavlink.lockstep_gcs import Gcs

FRAME = StorageFrame((4.0, -6.0, 0.0), math.radians(70))


def test_that_the_plan_holds_the_survey_waypoints_to_the_millimetre(tmp_path):
    m = Mission(p_traj=0.15, turn="two-step")
    rows = read_qgc_wpl(write_qgc_wpl(tmp_path / "p.waypoints", m, FRAME))
    nav = [r for r in rows if int(r[3]) == mavlink.MAV_CMD_NAV_WAYPOINT][1:]  # skip home
    wp = m.waypoints_w()  # W0 first: the copter takes off where it stands, and the survey starts at its start
    expected = FRAME.w_to_ned(np.column_stack([wp, np.full(len(wp), m.altitude_m)]))
    lat0, lon0, _ = DEFAULT_ORIGIN
    got = np.array([global_to_ned(r[8], r[9], lat0, lon0) for r in nav])
    assert np.allclose(got, expected[:, :2], atol=1e-3)
    assert all(r[10] == m.altitude_m for r in nav)
    assert [int(r[3]) for r in rows][:3] == [16, 178, 22] and int(rows[-1][3]) == 21


def test_that_the_plan_command_writes_a_file_and_refuses_bad_input(tmp_path, capsys):
    assert main(["plan", "--p-traj", "20", "--out", str(tmp_path / "p.waypoints")]) == 0
    assert (tmp_path / "p.waypoints").read_text().startswith("QGC WPL 110")
    assert main(["plan", "--p-traj", "60", "--out", str(tmp_path / "q.waypoints")]) == 2
    assert main(["serve", "--speedup", "0", "--out", str(tmp_path / "s")]) == 2
    assert main(["serve", "--mavlink", "tcp:nowhere", "--duration", "1", "--out", str(tmp_path / "s")]) == 2
    err = capsys.readouterr().err
    assert "P_traj" in err and "speedup" in err and "Traceback" not in err


def test_that_bad_plan_files_are_refused_with_the_line(tmp_path):
    bad = tmp_path / "bad.waypoints"
    bad.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\n")
    with pytest.raises(ValueError, match=":2:"):
        read_qgc_wpl(bad)
    bad.write_text("hello\n")
    with pytest.raises(ValueError, match="not a QGC WPL 110"):
        read_qgc_wpl(bad)


def _auto(vehicle, rows, tmp_path) -> Gcs:
    """A ground station on the vehicle that uploads the plan's rows over MAVLink, arms and switches to AUTO."""
    gcs = Gcs(vehicle, tlog_path=tmp_path / "t.tlog")
    items = [mavlink.MAVLink_mission_item_int_message(
        1, 1, i, int(r[2]), int(r[3]), 0, 1, r[4], r[5], r[6], r[7],
        round(r[8] * 1e7), round(r[9] * 1e7), r[10], 0) for i, r in enumerate(rows)]
    assert gcs.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.set_mode(FlightMode.AUTO) == mavlink.MAV_RESULT_ACCEPTED
    return gcs


def test_that_the_jsbsim_vehicle_flies_the_plan_uploaded_over_mavlink(tmp_path):
    m = Mission(p_traj=0.3)
    frame = StorageFrame()
    (n, e, _), _ = start_pose(m, frame)
    vehicle = JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(n, e, 0.0))))
    rows = read_qgc_wpl(write_qgc_wpl(tmp_path / "p.waypoints", m, frame))
    gcs = _auto(vehicle, rows, tmp_path)
    reached = {gcs.expect("MISSION_ITEM_REACHED", within_s=200).seq for _ in range(len(rows) - 1)}
    assert reached == set(range(1, len(rows)))
    gcs.run(5.0)
    assert vehicle.state().landed and not vehicle.state().armed


def _distance_to_rectangle_m(p_xy, x0: float, x1: float, y0: float, y1: float) -> float:
    """How far a point lies from the rectangle's outline (its four legs)."""
    x, y = p_xy
    legs = [(abs(y - yy), max(x0 - x, 0.0, x - x1)) for yy in (y0, y1)] + \
           [(abs(x - xx), max(y0 - y, 0.0, y - y1)) for xx in (x0, x1)]
    return min(math.hypot(a, b) for a, b in legs)


def test_that_a_plan_placed_at_a_rotated_site_loads_in_mavwp_and_lies_on_the_intended_rectangle(tmp_path):
    """`plan --origin -33.9,151.2,30 --heading 30`: pymavlink's own loader reads it, and every position in
    it, taken back into the storage frame about the site's corner, is on the P_traj 20 % rectangle."""
    from pymavlink import mavwp

    from firmware_py.core.site import Site

    out = tmp_path / "sydney.waypoints"
    assert main(["plan", "--p-traj", "20", "--origin", "-33.9,151.2,30", "--heading", "30", "--out", str(out),
                 "-q"]) == 0
    loader = mavwp.MAVWPLoader()
    n = loader.load(str(out))
    items = [loader.wp(i) for i in range(n)]
    site = Site.of(-33.9, 151.2, 30.0, 30.0)
    frame = site.frame_about()  # the EKF origin is the corner: the payload sends it so by default
    positioned = [it for it in items if it.command != mavlink.MAV_CMD_DO_CHANGE_SPEED]
    assert len(positioned) == n - 1 >= 7
    home, rest = positioned[0], positioned[1:]
    m = Mission(p_traj=0.20)
    wp = m.waypoints_w()
    (x0, y0), (x1, y1) = wp.min(axis=0), wp.max(axis=0)
    assert (x0, y0, x1, y1) == pytest.approx((12.0, 8.0, 48.0, 32.0))  # 20 % of 60 x 40 from the walls
    for it in positioned:
        north, east = site.corner.to_ned(it.x, it.y)
        up = it.z - site.corner.alt_m if it.frame == mavlink.MAV_FRAME_GLOBAL else it.z
        p_w = frame.ned_to_w([north, east, -up])
        assert _distance_to_rectangle_m(p_w[:2], x0, x1, y0, y1) < 0.1
    # Home and take-off on W0 (home on the floor), the loop from W0 in order at the survey altitude, landing on W0.
    got_w = np.array([frame.ned_to_w([*site.corner.to_ned(it.x, it.y), 0.0])[:2] for it in rest])
    assert np.abs(got_w[1:-1] - wp).max() < 0.1 and np.abs(got_w[[0, -1]] - wp[0]).max() < 0.1
    assert home.z == pytest.approx(site.corner.alt_m) and all(it.z == m.altitude_m for it in rest[:-1])
    # The building's x axis really is turned 30 deg east of north: W0 -> W1 is a leg along x.
    d = frame.w_to_ned(np.array([[wp[1][0], wp[1][1], 0.0]]))[0] - frame.w_to_ned(np.array([[*wp[0], 0.0]]))[0]
    n1, e1 = site.corner.to_ned(rest[2].x, rest[2].y)
    n0, e0 = site.corner.to_ned(rest[1].x, rest[1].y)
    assert math.degrees(math.atan2(e1 - e0, n1 - n0)) % 360 == pytest.approx(
        math.degrees(math.atan2(d[1], d[0])) % 360, abs=0.01)


def test_that_the_default_plan_is_the_one_placed_at_the_default_site(tmp_path):
    """No --origin / --heading: the plan is what it was before sites existed (the same file)."""
    assert main(["plan", "--p-traj", "20", "--out", str(tmp_path / "a.waypoints"), "-q"]) == 0
    assert main(["plan", "--p-traj", "20", "--origin", "53.4668,-2.2339,50", "--heading", "0",
                 "--out", str(tmp_path / "b.waypoints"), "-q"]) == 0
    assert (tmp_path / "a.waypoints").read_bytes() == (tmp_path / "b.waypoints").read_bytes()
    rows = read_qgc_wpl(tmp_path / "a.waypoints")
    assert (rows[0][8], rows[0][9]) == pytest.approx(
        frame_w0_global(Mission(p_traj=0.20), StorageFrame(), DEFAULT_ORIGIN), abs=1e-8)


def frame_w0_global(m: Mission, frame: StorageFrame, origin) -> tuple[float, float]:
    from firmware_py.core.geodesy import ned_to_global
    n, e, _ = frame.w_to_ned([*m.waypoints_w()[0], 0.0])
    return ned_to_global(n, e, origin[0], origin[1])


def test_that_a_plan_taking_off_away_from_the_first_waypoint_flies_there_before_the_survey_and_lands_back(tmp_path):
    """`serve` with material below W0 puts the vehicle on clear floor elsewhere (sitl.runners.serve.takeoff_spot):
    the plan's home and take-off are there, and W0 is the first waypoint, so the survey starts where it should; the
    loop ends over W0's material, so the plan flies back over the spot at the survey altitude and lands there."""
    m, frame, spot = Mission(p_traj=0.2), StorageFrame(), (24.375, 3.375)
    rows = read_qgc_wpl(write_qgc_wpl(tmp_path / "p.waypoints", m, frame, takeoff_w=spot))
    lat0, lon0, _ = DEFAULT_ORIGIN
    at = [frame.ned_to_w([*global_to_ned(r[8], r[9], lat0, lon0), 0.0])[:2] for r in rows]
    assert [int(r[3]) for r in rows][:4] == [16, 178, 22, 16]
    assert np.allclose(at[0], spot, atol=1e-3) and np.allclose(at[2], spot, atol=1e-3)  # home and take-off
    wp = m.waypoints_w()
    assert np.allclose(at[3], wp[0], atol=1e-3) and rows[3][10] == m.altitude_m  # then W0, at the survey altitude
    assert np.allclose(np.array(at[4:-2]), wp[1:], atol=1e-3) and len(rows) == len(wp) + 5
    assert [int(r[3]) for r in rows][-2:] == [16, 21] and rows[-2][10] == m.altitude_m and rows[-1][10] == 0.0
    assert np.allclose(at[-2], spot, atol=1e-3) and np.allclose(at[-1], spot, atol=1e-3)  # back over it, down there
    assert read_qgc_wpl(write_qgc_wpl(tmp_path / "w0.waypoints", m, frame))[3][8:10] == rows[3][8:10]  # as on W0
    n, e, _ = frame.w_to_ned([spot[0], spot[1], 0.0])
    vehicle = JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(float(n), float(e), 0.0))))
    gcs = _auto(vehicle, rows, tmp_path)
    assert gcs.expect("MISSION_ITEM_REACHED", within_s=5).seq == 1  # the speed set
    assert gcs.expect("MISSION_ITEM_REACHED", within_s=30).seq == 2  # climbed out over the spot
    p = frame.ned_to_w(vehicle.state().pos_ned_m)
    assert np.hypot(*(p[:2] - np.array(spot))) < 0.5 and p[2] == pytest.approx(m.altitude_m, abs=0.3)
    assert gcs.expect("MISSION_ITEM_REACHED", within_s=60).seq == 3  # then over W0
    p = frame.ned_to_w(vehicle.state().pos_ned_m)
    assert np.hypot(*(p[:2] - wp[0])) < 0.5 and p[2] == pytest.approx(m.altitude_m, abs=0.3)
