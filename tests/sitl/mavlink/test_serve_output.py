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
