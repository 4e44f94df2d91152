"""tools/noise_table: its options and its tables (the surveys themselves are the batch path's, tested there)."""

import pytest

from firmware_py.core.sensor_noise import SensorNoiseModel
from tools.noise_table import Case, costs, main, spot_table, table


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


def _rows(ve: list[float], applied: int = 0, ra: float = 95.0, no_return: float = 5.0, spikes: int = 0) -> list[dict]:
    return [{"phase": k, "ve_pct": v, "ve_nocal_pct": v, "self_cal_applied": k < applied, "ra_pct": ra,
             "spikes": spikes, "no_return_pct": no_return} for k, v in enumerate(ve)]


def test_that_the_costs_are_read_off_the_rows_and_name_what_costs_more_than_half_a_point():
    none, ds, aa = SensorNoiseModel.NONE, SensorNoiseModel.DATASHEET, SensorNoiseModel.APPENDIX_A
    results = {}
    for p in (5, 20, 30):
        for pile in ("1", "2"):
            results[Case(pile, p, none, phases=2)] = _rows([0.1, 0.3], ra=96.0, no_return=4.0)
            results[Case(pile, p, ds, phases=2)] = _rows([0.2, 0.4] if p < 30 else [3.0, 4.0], ra=80.0,
                                                         no_return=20.0, spikes=3)
            results[Case(pile, p, aa, phases=2)] = _rows([0.3, 0.5], applied=1 if (pile, p) == ("2", 5) else 0)
    spot = {"pile": "1", "p": 30, "model": ds, "phase": 1, "ve_pct": 3.5, "self_cal_applied": False,
            "ve_nocal_pct": 3.5, "no_return_pct": 21.0, "wall_s": 9.0}
    text = costs(results, [spot])
    assert "1 of the 24 noisy surveys" in text  # pile 2 at 5 % under Appendix A applied one
    assert "**P_traj 5 %**: the noise moves the mean Ve by +0.10 to +0.20 pp" in text
    assert "more than 0.5 pp" not in text.split("**P_traj 30 %**")[0]
    assert "more than 0.5 pp: pile 2 datasheet +3.30 pp, pile 1 datasheet +3.30 pp." in text
    assert "20.0 / 20.0 / 20.0 % of pile 1's samples" in text and "(4.0 / 4.0 / 4.0 % without noise" in text
    assert "pile 1 96.0 -> 80.0 %, Ve 3.50 ± 0.50 % (max 4.00 %)" in text
    assert "removed 36 samples in all 24 noisy surveys" in text  # 3 in each datasheet survey
    assert "pile 1 P_traj 30 % datasheet 3.50 / 4.00" in text and "sd 0.50 pp" in text
    assert "in 0 of the firmware flights" in text
