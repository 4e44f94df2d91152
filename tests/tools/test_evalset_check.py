"""The command every evaluation-set check shares (`tools.evalset_check`): its P_traj option only where a check takes
it, the runs it chooses, and the regenerate line it writes."""

import json
from pathlib import Path

import pytest

from tests.tools.golden_run import store_golden_run
from tools.evalset_check import EvalsetCheck, check_main


def _row(run_dir: str) -> dict:
    truth = json.loads((Path(run_dir) / "truth.json").read_text())
    return {"noise": truth["noise"], "p_traj": truth["p_traj_pct"]}


def _summary(rows) -> list[str]:
    return [f"| {r['noise']} | {r['p_traj']} |" for r in rows]


def _check(p_traj: bool) -> EvalsetCheck:
    return EvalsetCheck("some_check", "some-check", _row, _summary, ("none",), "noise models", p_traj=p_traj)


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    root = tmp_path_factory.mktemp("evalset")
    store_golden_run(root, true_volume_m3=1.0, p_traj_pct=20)
    return root


def test_that_a_check_taking_p_traj_chooses_by_it_and_says_it_in_the_regenerate_line(stored, tmp_path, capsys):
    page = tmp_path / "page.md"
    page.write_text("<!-- some-check:start -->\n<!-- some-check:end -->\n")
    assert check_main(_check(True), None, ["--root", str(stored), "--p-traj", "20", "--write", str(page)]) == 0
    assert "| none | 20 |" in capsys.readouterr().out
    assert "`python -m tools.some_check --p-traj 20 --jobs 1 --write" in page.read_text()
    assert check_main(_check(True), None, ["--root", str(stored), "--p-traj", "30"]) == 2
    assert "no stored runs with noise none" in capsys.readouterr().err


def test_that_a_check_without_p_traj_refuses_the_option(stored):
    with pytest.raises(SystemExit) as exc:
        check_main(_check(False), None, ["--root", str(stored), "--p-traj", "20"])
    assert exc.value.code == 2
