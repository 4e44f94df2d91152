"""tools.estimator_evalset: the estimators' table over stored runs of the evaluation set."""

import pytest

from tools.estimator_compare import ESTIMATORS
from tools.estimator_evalset import main, table


def test_that_the_table_gives_each_group_its_mean_absolute_and_signed_error_per_estimator():
    rows = [{"noise": "none", **{n: v for n in ESTIMATORS}} for v in (1.0, -3.0)]
    rows.append({"noise": "datasheet", **{n: 2.0 for n in ESTIMATORS}})
    lines = table(rows, "noise").splitlines()
    assert lines[0].count("mean abs Ve") == len(ESTIMATORS)
    none = next(line for line in lines if line.startswith("| none |"))
    assert none.startswith("| none | 2 | 2.00 (-1.00) |")
    sheet = next(line for line in lines if line.startswith("| datasheet |"))
    assert sheet.startswith("| datasheet | 1 | 2.00 (+2.00) |")


def test_that_an_empty_evaluation_set_is_one_clear_line(tmp_path, capsys):
    (tmp_path / "runs").mkdir()
    assert main(["--root", str(tmp_path)]) == 2
    assert "no stored runs" in capsys.readouterr().err


def test_that_a_missing_evaluation_set_is_one_clear_line(tmp_path, capsys):
    assert main(["--root", str(tmp_path / "nowhere")]) == 2
    assert "no evaluation set" in capsys.readouterr().err


def test_that_a_missing_rows_file_is_one_clear_line(tmp_path, capsys):
    assert main(["--from-rows", str(tmp_path / "none.csv")]) == 2
    assert "no rows file" in capsys.readouterr().err


def test_that_a_bad_job_count_is_refused():
    with pytest.raises(SystemExit):
        main(["--jobs", "0"])


def test_that_a_rows_file_that_is_not_text_is_one_clear_line(tmp_path, capsys):
    rows = tmp_path / "rows.csv"
    rows.write_bytes(b"\xff\xfe\x00binary")
    assert main(["--from-rows", str(rows)]) == 2
    assert str(rows) in capsys.readouterr().err
