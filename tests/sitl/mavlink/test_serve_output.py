"""What `pilescan-sitl serve` tells its operator, and its --tlog-max-mb option."""

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
