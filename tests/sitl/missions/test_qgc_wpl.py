"""The exported plan: a valid QGC WPL 110 file whose positions are the survey's, flyable over MAVLink."""

import math

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.core.frames import StorageFrame
from sitl.cli import main
from sitl.mavlink.geodesy import global_to_ned
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
    wp = m.waypoints_w()
    expected = FRAME.w_to_ned(np.column_stack([wp[1:], np.full(len(wp) - 1, m.altitude_m)]))
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


def test_that_the_jsbsim_vehicle_flies_the_plan_uploaded_over_mavlink(tmp_path):
    m = Mission(p_traj=0.3)
    frame = StorageFrame()
    (n, e, _), _ = start_pose(m, frame)
    vehicle = JsbsimVehicle(VehicleConfig(plant=PlantConfig(start_ned_m=(n, e, 0.0))))
    gcs = Gcs(vehicle, tlog_path=tmp_path / "t.tlog")
    rows = read_qgc_wpl(write_qgc_wpl(tmp_path / "p.waypoints", m, frame))
    items = [mavlink.MAVLink_mission_item_int_message(
        1, 1, i, int(r[2]), int(r[3]), 0, 1, r[4], r[5], r[6], r[7],
        round(r[8] * 1e7), round(r[9] * 1e7), r[10], 0) for i, r in enumerate(rows)]
    assert gcs.upload(items) == mavlink.MAV_MISSION_ACCEPTED
    assert gcs.command(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1) == mavlink.MAV_RESULT_ACCEPTED
    assert gcs.set_mode(FlightMode.AUTO) == mavlink.MAV_RESULT_ACCEPTED
    reached = {gcs.expect("MISSION_ITEM_REACHED", within_s=200).seq for _ in range(len(rows) - 1)}
    assert reached == set(range(1, len(rows)))
    gcs.run(5.0)
    assert vehicle.state().landed and not vehicle.state().armed
