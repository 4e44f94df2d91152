"""tools/estimator_compare: its options and its tables (the surveys are the batch path's, tested there)."""

import pytest

from firmware_py.core.sensor_noise import SensorNoiseModel
from tools.estimator_compare import ESTIMATORS, Case, main, must_show, table


@pytest.mark.parametrize("argv", [["--phases", "0"], ["--phases", "21"], ["--jobs", "0"], ["--models", "gaussian"]])
def test_that_bad_options_are_one_line_and_exit_2(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    err = capsys.readouterr().err
    assert exc.value.code == 2 and "Traceback" not in err and err.count("\n") <= 2


def _rows(values):
    return [{"phase": k, **{n: v for n in ESTIMATORS}} for k, v in enumerate(values)]


def test_that_the_table_gives_mean_sd_of_ve_and_the_signed_mean_and_the_target_counts_each_p_traj():
    clean = Case("1", 5, SensorNoiseModel.NONE, phases=2)
    noisy = Case("1", 5, SensorNoiseModel.APPENDIX_A, phases=2)
    far = Case("1", 10, SensorNoiseModel.NONE, phases=2)
    far_noisy = Case("1", 10, SensorNoiseModel.APPENDIX_A, phases=2)
    results = {clean: _rows([0.1, -0.1]), noisy: _rows([0.15, 0.25]),
               far: _rows([0.0, 0.0]), far_noisy: _rows([1.0, 1.0])}
    text = table(results)
    assert "| 1 | 5 % | none | 0.10 ± 0.00 (+0.00) |" in text
    assert "| 1 | 5 % | appendix-a | 0.20 ± 0.05 (+0.20) |" in text
    target = must_show(results)
    assert "| cubic-limited | 1 | appendix-a | +1.00 | 1 of 2 |" in target  # 5 %: +0.10 pp (within), 10 %: +1.00
