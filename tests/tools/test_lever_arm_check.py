"""The lever-arm check over stored evaluation runs: each run reported with its own lever arm and with it moved along a
body axis, the change of volume against the run's own report, the interval's coverage and the new warnings."""

import json

import pytest

from tests.tools.golden_run import RUN, golden_true_volume_m3, store_golden_run
from tools.lever_arm_check import lever_rows, main, summary, warning_lines


@pytest.fixture(scope="module")
def stored(tmp_path_factory):
    """The golden flight stored as an evaluation run (samples.npy, header.json, truth.json)."""
    root = tmp_path_factory.mktemp("evalset")
    store_golden_run(root, true_volume_m3=golden_true_volume_m3())
    return root


def test_that_a_lever_arm_entered_too_far_down_lowers_the_volume_and_is_warned_and_too_short_raises_it(stored):
    rows = {r["offset_m"]: r for r in lever_rows(str(stored / "runs" / RUN), [0.2], axes=("z",))}
    assert sorted(rows) == [-0.2, 0.2] and {r["axis"] for r in rows.values()} == {"z"}
    low, high = rows[0.2], rows[-0.2]  # +z is down: entered 0.2 m too far down, every point 0.2 m low
    assert low["volume_m3"] < 0.97 * low["base_volume_m3"]
    assert any(w.startswith("the floor the sweeps saw") for w in low["new_warnings"])
    assert high["volume_m3"] > 1.03 * high["base_volume_m3"]
    assert low["base_volume_m3"] == high["base_volume_m3"]


def test_that_the_table_gives_the_change_of_ve_against_the_right_lever_arm_and_counts_coverage_and_warnings():
    def row(off, vol, covered, warned):
        return {"run": "a", "family": "cone", "noise": "none", "axis": "x", "offset_m": off, "volume_m3": vol,
                "base_volume_m3": 1000.0, "true_volume_m3": 1000.0, "covered": covered,
                "new_warnings": ["pose corrected"] if warned else []}
    rows = [row(0.1, 1010.0, True, False), row(0.1, 1030.0, False, True), row(-0.1, 995.0, True, False)]
    rows.append(dict(row(0.1, 1100.0, True, False), noise="datasheet"))
    lines = summary(rows)
    assert "median / 90th pct" in lines[0] and lines[0].index("datasheet") < lines[0].index("none")
    assert "| x -10 cm | - | 0.50 / 0.50 pp (1) | 1 of 1 | 0 of 1 |" in lines
    assert "| x +10 cm | 10.00 / 10.00 pp (1) | 2.00 / 2.80 pp (2) | 2 of 3 | 1 of 3 |" in lines
    assert warning_lines(rows) == ['- "pose corrected...": 1 of 4']
    empty = [dict(row(0.1, 3.0, True, False), true_volume_m3=0.0)]  # an empty building: no Ve to change
    assert "| x +10 cm | - | 1 of 1 | 0 of 1 |" in summary(empty)


def test_that_the_command_prints_the_table_writes_it_into_its_section_and_refuses_bad_options(stored, tmp_path,
                                                                                               capsys):
    page = tmp_path / "page.md"
    page.write_text("before\n<!-- lever-arm:start -->\nold\n<!-- lever-arm:end -->\nafter\n")
    rows = tmp_path / "rows.json"
    assert main(["--root", str(stored), "--stride", "1", "--offsets", "0.2", "--axes", "z", "--write", str(page),
                 "--rows", str(rows)]) == 0
    out = capsys.readouterr().out
    assert "| z -20 cm | " in out and "| z +20 cm | " in out and "| x " not in out and "pp (1) |" in out
    text = page.read_text()
    assert "old" not in text and text.startswith("before\n") and text.endswith("after\n")
    assert "`python -m tools.lever_arm_check --offsets 0.2 --stride 1 --axes z` (1 run of the evaluation set)" in text
    assert len(json.loads(rows.read_text())) == 2
    for bad in (["--stride", "0"], ["--offsets", "0"], ["--offsets", "x"], ["--offsets", "2"], ["--axes", "w"]):
        assert main(["--root", str(stored), *bad]) == 2
    assert main(["--root", str(tmp_path)]) == 2
    assert "lever_arm_check:" in capsys.readouterr().err
