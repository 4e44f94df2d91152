"""tools/noise_table: its options and its tables (the surveys themselves are the batch path's, tested there)."""

import pytest

from firmware_py.core.sensor_noise import SensorNoiseModel
from tools.noise_table import Case, main, spot_table, table


@pytest.mark.parametrize("spot", ["1,20,datasheet", "3,20,none,0", "1,25,none,0", "1,20,gaussian,0", "1,20,none,20"])
def test_that_a_bad_spot_check_is_one_line_and_exit_2(spot, capsys):
    with pytest.raises(SystemExit) as exc:
        main(["--spot", spot])
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "--spot must be PILE,P_TRAJ,MODEL,PHASE" in err and "Traceback" not in err


def test_that_the_table_states_mean_sd_max_and_the_false_corrections():
    rows = [{"phase": k, "ve_pct": ve, "ve_nocal_pct": nocal, "self_cal_applied": nocal != ve, "ra_pct": 95.0,
             "spikes": 0, "no_return_pct": 5.0} for k, (ve, nocal) in enumerate([(1.0, 1.0), (3.0, 2.0)])]
    case = Case("1", 20, SensorNoiseModel.DATASHEET, phases=2)
    text = table({case: rows})
    assert "| 1 | 20 % | datasheet | 2.00 ± 1.00 | 3.00 | 1.50 ± 0.50 | 1 of 2 | 95.0 | 5.0 | 0 |" in text
    spot = {"pile": "1", "p": 20, "model": SensorNoiseModel.DATASHEET, "phase": 1, "ve_pct": 2.5,
            "self_cal_applied": False, "ve_nocal_pct": 2.5, "no_return_pct": 6.0, "wall_s": 40.0}
    want = "| 1 | 20 % | datasheet | 1 | 2.50 | 3.00 | no | 2.50 | 2.00 | 6.0 | 40 |"
    assert want in spot_table([spot], {case: rows})
