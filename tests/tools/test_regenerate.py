"""`python -m tools.regenerate`: every page a change of the volumes touches, regenerated in dependency order,
resumably."""

import importlib.util
import json
from pathlib import Path

import pytest

from tools.regenerate import POSE_RUNS, STEP_NAMES, STEPS, Step, load_state, main, move_pose_reports_aside, run_steps

ROOT = Path(__file__).resolve().parents[2]


def test_that_every_step_runs_a_tool_that_exists():
    for step in STEPS:
        if step.argv is not None:
            assert importlib.util.find_spec(step.argv[0]) is not None, step.name


def test_that_every_page_a_step_writes_is_in_the_repository():
    for step in STEPS:
        for page in step.pages:
            assert (ROOT / page).exists(), (step.name, page)


def test_that_each_page_names_the_tool_that_regenerates_it():
    """The steps and the pages cannot drift apart silently: a page says which tool made it."""
    for step in STEPS:
        pages = [p for p in step.pages if p.endswith(".md") and p != "README.md"]
        if step.argv is None or not pages:
            continue
        assert any(f"python -m {step.argv[0]}" in (ROOT / p).read_text(encoding="utf-8") for p in pages), step.name


def test_that_the_steps_come_in_the_order_their_figures_depend_on():
    order = {name: i for i, name in enumerate(STEP_NAMES)}
    assert order["evalset"] == 0 and order["interval"] == 1  # the runs it is fitted on; its factors are in every report
    campaigns = [n for n in STEP_NAMES if n.startswith("pose") and n not in ("pose-reports-aside", "pose-interval")]
    assert all(order["pose-reports-aside"] < order[n] for n in campaigns)
    assert all(order[n] < order["pose-interval"] for n in ("pose", "pose-own", "pose-hidden", "pose-datasheet",
                                                              "pose-appendix-a"))
    assert len(set(STEP_NAMES)) == len(STEP_NAMES)


def _toy(name: str, ok: bool) -> Step:
    """A step that succeeds (`python -m json.tool --help`) or fails (a file that is not there)."""
    return Step(name, ("json.tool", "--help") if ok else ("json.tool", "/no/such/file.json"), ())


def test_that_a_run_stops_at_a_failure_and_resumes_after_the_steps_done(tmp_path):
    said = []
    steps = [_toy("a", True), _toy("b", False), _toy("c", True)]
    assert run_steps(steps, tmp_path, say=said.append) == 1
    state = load_state(tmp_path / "state.json")
    assert state["a"]["ok"] and not state["b"]["ok"] and "c" not in state  # stopped at b
    assert (tmp_path / "a.log").read_text() and (tmp_path / "b.log").exists()
    said.clear()
    fixed = [_toy("a", True), _toy("b", True), _toy("c", True)]
    assert run_steps(fixed, tmp_path, say=said.append) == 0
    assert said[0] == "a: done before, skipped"  # resumed: a is not run again
    assert all(load_state(tmp_path / "state.json")[n]["ok"] for n in "abc")


def test_that_keep_going_runs_the_steps_after_a_failure(tmp_path):
    steps = [_toy("a", False), _toy("b", True)]
    assert run_steps(steps, tmp_path, keep_going=True, say=lambda _: None) == 1
    assert load_state(tmp_path / "state.json")["b"]["ok"]


def test_that_the_kept_pose_reports_are_moved_aside_and_the_flights_stay(tmp_path):
    runs = tmp_path / POSE_RUNS[0]
    for name in ("flow-1-20-0", "flow-1-20-0--no-pose-correction", "flow-1-20-0--pose-correction",
                 "flow-1-20-0--true-height"):
        (runs / name).mkdir(parents=True)
    assert move_pose_reports_aside(tmp_path, tmp_path / "aside") == 3
    assert [p.name for p in runs.iterdir()] == ["flow-1-20-0"]
    assert (tmp_path / "aside" / "pose__flow-1-20-0--true-height").is_dir()


@pytest.mark.parametrize("text", ["{not json", "[1, 2]", '{"interval": 3}'])
def test_that_a_damaged_state_is_a_clear_error(tmp_path, text):
    (tmp_path / "state.json").write_text(text)
    with pytest.raises(SystemExit, match="not a state this tool wrote"):
        load_state(tmp_path / "state.json")


def test_that_the_list_says_what_is_done(tmp_path, capsys):
    (tmp_path / "state.json").write_text(json.dumps({"interval": {"ok": True}}))
    assert main(["--list", "--state", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "interval             done" in out and "golden               to do" in out
    assert "python -m tools.reproduce --experiments baseline,noise" in out


def test_that_fresh_forgets_only_the_chosen_steps(tmp_path):
    (tmp_path / "state.json").write_text(json.dumps({"interval": {"ok": True}, "golden": {"ok": True}}))
    assert main(["--fresh", "--only", "golden", "--list", "--state", str(tmp_path)]) == 0  # --list changes nothing
    assert load_state(tmp_path / "state.json")["golden"]["ok"]
