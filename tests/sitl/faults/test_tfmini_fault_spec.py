"""The TFMini's faults as settings: parsed like the others, checked against the rangefinder flown."""

import json
import math

import pytest

from firmware_py.core.sensor import Rangefinder
from sitl.faults.injector import FaultSpec
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig
from sitl.runners.serve import ServeOptions


def test_that_tfmini_faults_parse_from_the_command_line_form_and_an_endless_unplug_is_json():
    spec = FaultSpec.parse(["tfmini_bad_frame_pct=2", "tfmini-garbage-pct=1.5", "tfmini_unplug=30,inf"], seed=4)
    assert (spec.tfmini_bad_frame_pct, spec.tfmini_garbage_pct) == (2.0, 1.5)
    assert spec.tfmini_unplug[0] == 30.0 and math.isinf(spec.tfmini_unplug[1])
    assert json.loads(json.dumps(spec.to_dict(), allow_nan=False))["tfmini_unplug"] == [30.0, None]


@pytest.mark.parametrize("item", ["tfmini_unplug=5,0", "tfmini_unplug=-1,2", "tfmini_unplug=5", "tfmini_unplug=5,nan",
                                  "tfmini_bad_frame_pct=101", "tfmini_garbage_pct=-1"])
def test_that_bad_tfmini_faults_are_refused_naming_the_fault(item):
    with pytest.raises(ValueError, match="tfmini_"):
        FaultSpec.parse([item])


def test_that_a_fault_of_the_other_rangefinder_is_refused():
    with pytest.raises(ValueError, match="i2c_nack_pct acts on the LIDAR-Lite"):
        FlyConfig(payload="firmware", rangefinder=Rangefinder.TFMINI, faults=FaultSpec(i2c_nack_pct=5))
    with pytest.raises(ValueError, match="tfmini_unplug acts on the TFMini"):
        FlyConfig(payload="firmware", faults=FaultSpec(tfmini_unplug=(5.0, 2.0)))


def test_that_serve_takes_a_tfmini_only_with_its_devices():
    with pytest.raises(ValueError, match="needs --devices"):
        ServeOptions(mission=Mission(), rangefinder=Rangefinder.TFMINI)
    opts = ServeOptions(mission=Mission(), devices_url="tcp:127.0.0.1:0", rangefinder=Rangefinder.TFMINI,
                        faults=FaultSpec(tfmini_unplug=(5.0, 2.0)))
    assert opts.fly_config().lidar.max_range_m == 12.0  # the world is ray cast to the TFMini's range


@pytest.mark.parametrize(("argv", "words"), [
    (["fly", "--stockpile", "1", "--p-traj", "20", "--rangefinder", "sonar"], "unknown rangefinder"),
    (["fly", "--stockpile", "1", "--p-traj", "20", "--rangefinder", "tfmini"], "mostly out of range"),
    (["fly", "--stockpile", "1", "--p-traj", "20", "--rangefinder", "tfmini", "--storage", "30x20x10", "--altitude",
      "9", "--fault", "lidar_stuck_busy=5,2"], "acts on the LIDAR-Lite"),
    (["serve", "--rangefinder", "tfmini", "--duration", "1"], "needs --devices"),
])
def test_that_bad_tfmini_sitl_options_are_one_line_and_exit_2(capsys, tmp_path, argv, words):
    from sitl.cli import main
    rc = main([*argv, "--out", str(tmp_path / "run")])
    err = capsys.readouterr().err
    assert rc == 2 and words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "run" / "truth.json").exists()
