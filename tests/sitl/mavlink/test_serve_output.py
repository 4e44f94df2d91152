"""What `pilescan-sitl serve` tells its operator (the payload's command line too), and its --tlog-max-mb option."""

import pytest

from sitl.cli import main


def test_that_serve_says_where_it_listens_that_it_records_no_lidar_data_and_when_it_stops(tmp_path, capsys):
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--duration", "0.3",
                 "--speedup", "20", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 0, err
    lines = err.splitlines()
    assert lines[0].startswith("pilescan-sitl: serving a kinematic quadcopter on udp:127.0.0.1:0 "
                               "(listening at 127.0.0.1:")
    assert "this run records no LiDAR data" in lines[1] and "--devices" in lines[1]
    assert lines[-1].startswith("pilescan-sitl: stopped after ")


def test_that_a_tlog_cap_that_is_not_positive_is_refused_in_one_line(tmp_path, capsys):
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--duration", "0.3",
                 "--tlog-max-mb", "0", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 2 and "--tlog-max-mb must be > 0" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "s").exists()


def test_that_serve_flies_a_sensor_noise_model_says_so_and_records_it_in_the_truth(tmp_path, capsys):
    import json

    from pymavlink import mavutil

    out = tmp_path / "s"
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--devices", "tcp:127.0.0.1:0",
                 "--duration", "1.5", "--sensor-noise", "appendix-a", "--seed", "2", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    assert "pilescan-sitl: sensor noise: appendix-a (appendix-a: range 2.5 cm, servo angle 1 deg" in err
    assert json.loads((out / "truth.json").read_text())["sensor_noise"]["position_sigma_m"] == 0.113
    tlog = mavutil.mavlink_connection(str(out / "telemetry.tlog"))
    rolls = []
    while (m := tlog.recv_match(type="ATTITUDE")) is not None:
        rolls.append(m.roll)
    assert rolls and all(r != 0.0 for r in rolls)  # the vehicle stands level; what it reports is noisy


def _printed_payload(err: str) -> list[str]:
    """The payload's command line serve printed, split as a shell would."""
    import shlex

    (line,) = [line for line in err.splitlines() if "run the payload with: " in line]
    return shlex.split(line.split("run the payload with: ", 1)[1])


def _payload_config(argv: list[str]):
    """What pilescan-payload makes of argv: its own parser, and the checks it runs before opening anything."""
    from firmware_py.cli import build_parser, config_from_args

    assert argv[0] == "pilescan-payload"
    return config_from_args(build_parser().parse_args(argv[1:]))


@pytest.mark.parametrize("rangefinder", ["lidarlite-v3", "tfmini"])
def test_that_the_payload_command_line_serve_prints_runs_as_printed_for_this_survey(tmp_path, capsys, rangefinder):
    import re

    from firmware_py.core.rundir import SAMPLES_FILE
    from firmware_py.core.sensor import Rangefinder
    from firmware_py.core.storage import Storage

    out = tmp_path / "s"
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--devices", "tcp:127.0.0.1:0",
                 "--rangefinder", rangefinder, "--storage", "30x20x10", "--altitude", "9", "--p-traj", "25",
                 "--duration", "0.3", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 0, err
    mavlink_port = re.search(r"listening at 127\.0\.0\.1:(\d+)", err).group(1)
    bridge = re.search(r"LiDAR and servo on (tcp:127\.0\.0\.1:\d+)", err).group(1)
    cfg = _payload_config(_printed_payload(err))
    assert cfg.mavlink_url == f"udpout:127.0.0.1:{mavlink_port}"
    assert cfg.storage == Storage(30.0, 20.0, 10.0)  # not the payload's default building
    assert cfg.out_path == str(out / SAMPLES_FILE) and cfg.stop_on_disarm
    assert cfg.pwm_url == f"pwm:{bridge}:0"
    if rangefinder == "tfmini":
        pty = re.search(r"TFMini on (/dev/[^\s:]+): ", err).group(1)  # as tools.fly_networked reads it
        assert cfg.rangefinder is Rangefinder.TFMINI and cfg.uart_url == f"serial:{pty}"
    else:
        assert cfg.rangefinder is Rangefinder.LIDARLITE_V3 and cfg.i2c_url == bridge
    assert cfg.site is None  # the default site: the payload takes the served EKF origin as the corner


def test_that_the_printed_payload_command_carries_the_site_and_the_key_file(tmp_path, capsys):
    import math

    key = tmp_path / "link.key"
    key.write_text(bytes(range(1, 33)).hex() + "\n")
    key.chmod(0o600)
    code = main(["serve", "--vehicle", "kinematic", "--mavlink", "udp:127.0.0.1:0", "--devices", "tcp:127.0.0.1:0",
                 "--rangefinder", "tfmini", "--storage", "30x20x10", "--altitude", "9", "--p-traj", "25",
                 "--origin=-33.8688123,151.2093456,12.5", "--heading=-20.25", "--signing-key", str(key),
                 "--duration", "0.3", "--out", str(tmp_path / "s")])
    err = capsys.readouterr().err
    assert code == 0, err
    cfg = _payload_config(_printed_payload(err))
    c = cfg.site.corner
    assert (c.lat_deg, c.lon_deg, c.alt_m) == (-33.8688123, 151.2093456, 12.5)
    assert cfg.site.heading_rad == math.radians(-20.25)
    assert cfg.signing is not None and cfg.signing.key == bytes(range(1, 33))


def test_that_a_vehicle_whose_first_waypoint_is_over_the_pile_waits_on_the_nearest_clear_floor():
    """The served vehicle waited on the floor below W0; at P_traj 20 % pile 1 stands 4.5 m over that spot, so the
    simulator's vehicle sat inside the material and the payload's first samples saw the pile from within. It now
    waits where an operator would put it: the nearest floor clear all round it, away from the walls."""
    import numpy as np

    from firmware_py.core.storage import Storage
    from sitl.missions.rectangle import Mission
    from sitl.runners.serve import TAKEOFF_CLEAR_M, footprint_w, material_m, takeoff_spot, takeoff_under_pile
    from sitl.world.clearance import f450_reach_m
    from sitl.world.raycast import World
    from sitl.world.shapes import make_shape
    from sitl.world.stockpile import paper_pile
    st = Storage(60, 40, 15)
    world, mission = World(st, paper_pile("1", st)), Mission(storage=st, p_traj=0.2)
    spot = takeoff_spot(mission, world)
    assert spot is not None and spot.material_at_w0_m == pytest.approx(4.47, abs=0.01)
    x, y = spot.xy_w
    reach, margin = f450_reach_m(), f450_reach_m() + mission.min_clearance_m
    assert margin <= x <= st.length_m - margin and margin <= y <= st.width_m - margin
    assert (material_m(world, footprint_w((x, y), reach)) <= TAKEOFF_CLEAR_M).all()  # clear all round the vehicle
    d = np.hypot(x - 12.0, y - 8.0)
    probe = np.array([[12.0 + r * np.cos(a), 8.0 + r * np.sin(a)] for r in np.arange(0.5, d - 0.5, 0.5)
                      for a in np.linspace(0, 2 * np.pi, 72, endpoint=False)])
    inside = (probe[:, 0] > margin) & (probe[:, 0] < st.length_m - margin) & (probe[:, 1] > margin) \
        & (probe[:, 1] < st.width_m - margin)
    assert (material_m(world, probe[inside]) > TAKEOFF_CLEAR_M).all()  # nothing clear nearer W0
    assert "(12.0, 8.0) m" in spot.describe((12.0, 8.0)) and "4.47 m" in spot.describe((12.0, 8.0))
    cone = World(st, make_shape("cone", st, 8.0, seed=0).pile)  # a cone in the middle: W0 on bare floor
    assert takeoff_spot(Mission(storage=st, p_traj=0.05), cone) is None
    assert takeoff_under_pile(Mission(storage=st, p_traj=0.05), cone) is None
    small = Storage(20, 14, 10)  # material wall to wall: nowhere clear, so the old warning
    everywhere = World(small, paper_pile("2", small))
    wall_to_wall = Mission(storage=small, p_traj=0.2, altitude_m=9.0)
    assert takeoff_spot(wall_to_wall, everywhere) is None
    assert "no clear floor was found" in takeoff_under_pile(wall_to_wall, everywhere)
