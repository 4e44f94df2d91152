"""tools.slopes_evalset: the default slopes against the GP's and the GP's at the bridges on stored runs, each noisy run
against its twin."""

import pytest

from tools.slopes_evalset import main, noise_shares, share_table, table, twin_id


def _row(run_id: str, noise: str, curvature: float, gp: float, bridges: float | None = None, family: str = "cone",
         p: int = 30) -> dict:
    return {"run_id": run_id, "family": family, "building": "paper", "p_traj_pct": p, "noise": noise,
            "split": "heldout", "curvature": curvature, "gp": gp, "gp-bridges": gp if bridges is None else bridges,
            "curvature_s": 1.0, "gp_s": 3.0, "gp-bridges_s": 1.5}


def test_that_a_noisy_run_is_paired_with_the_noise_free_run_of_its_pile_flight_and_phase():
    assert twin_id("paper-cone-0-a12-p30-ph4-appendix-a", "appendix-a") == "paper-cone-0-a12-p30-ph4-none"
    assert twin_id("paper-cone-0-a12-p30-ph4-datasheet", "datasheet") == "paper-cone-0-a12-p30-ph4-none"
    with pytest.raises(ValueError, match="does not end"):
        twin_id("paper-cone-0-a12-p30-ph4-datasheet", "appendix-a")


def test_that_the_noise_share_is_each_slopes_distance_from_its_own_twin():
    rows = [_row("x-ph1-none", "none", 1.0, 1.1, 0.9), _row("x-ph1-datasheet", "datasheet", -1.0, 1.3, 1.4),
            _row("y-ph2-appendix-a", "appendix-a", 5.0, 5.0)]  # y's twin is not stored: left out
    [share] = noise_shares(rows)
    assert share["noise"] == "datasheet"
    assert share["curvature"] == pytest.approx(2.0)
    assert share["gp"] == pytest.approx(0.2)
    assert share["gp-bridges"] == pytest.approx(0.5)


def test_that_the_tables_count_runs_within_the_target_and_leave_out_faces():
    def share(family, curvature, gp, bridges):
        return {"noise": "appendix-a", "family": family, "p_traj_pct": 30, "curvature": curvature, "gp": gp,
                "gp-bridges": bridges}
    shares = [share("cone", 0.5, 0.1, 0.4), share("cone", 0.1, 0.3, 0.1), share("box", 9.0, 9.0, 9.0)]
    line = next(x for x in share_table(shares, "p_traj_pct").splitlines() if x.startswith("| appendix-a |"))
    assert line == "| appendix-a | 30 | 2 | 0.25 / 0.30 / 0.20 | 0.25 / 0.30 / 0.20 | 1 / 1 / 1 |"
    rows = [_row("a-none", "none", -1.0, 3.0, 2.0), _row("b-none", "none", 1.0, 1.0, -1.0),
            _row("c-none", "none", 50.0, 50.0, family="sphere")]
    line = next(x for x in table(rows, "noise").splitlines() if x.startswith("| none |"))
    assert line == "| none | 2 | 1.50 / 1.00 / 2.00 | +0.50 / +0.00 / +2.00 |"


def test_that_rows_read_back_give_the_same_tables(tmp_path, capsys):
    from tools.sweep import write_rows_csv

    rows = [_row("x-ph1-none", "none", 1.0, 1.1), _row("x-ph1-datasheet", "datasheet", -1.0, 1.3)]
    write_rows_csv(rows, tmp_path / "rows.csv")
    page = tmp_path / "page.md"
    assert main(["--from-rows", str(tmp_path / "rows.csv"), "--write", str(page)]) == 0
    text = page.read_text()
    assert "| datasheet | 30 | 1 | 0.20 / 2.00 / 0.20 | 0.20 / 2.00 / 0.20 | 1 / 0 / 1 |" in text
    assert "<!-- slopes-evalset:start -->" in text


def test_that_a_missing_or_empty_evaluation_set_is_one_clear_line(tmp_path, capsys):
    assert main(["--root", str(tmp_path / "nowhere")]) == 2
    assert "no evaluation set" in capsys.readouterr().err
    (tmp_path / "runs").mkdir()
    assert main(["--root", str(tmp_path)]) == 2
    assert "no stored runs" in capsys.readouterr().err
    assert main(["--from-rows", str(tmp_path / "none.csv")]) == 2
    assert "no rows file" in capsys.readouterr().err


@pytest.mark.parametrize("content", [b"run_id,family\nx,cone\n", b"\xff\xfe\x00binary", b""])
def test_that_a_rows_file_of_another_tool_or_none_at_all_is_one_clear_line(tmp_path, capsys, content):
    rows = tmp_path / "rows.csv"
    rows.write_bytes(content)
    assert main(["--from-rows", str(rows)]) == 2
    err = capsys.readouterr().err
    assert str(rows) in err or "no runs" in err
    assert "Traceback" not in err
