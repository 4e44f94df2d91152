"""Two flights of one survey end to end (ideal plant): a short first flight, `--fill-gaps` from its report, and
the merged report of both logs."""

import json

from ground.cli import main as ground
from sitl.cli import main as sitl

SMALL = ["--storage", "30x20x10", "--altitude", "8", "--plant", "ideal", "--stockpile", "1"]


def test_that_a_gap_re_flight_merged_with_the_first_flight_sees_what_the_first_missed(tmp_path):
    run1, run2 = tmp_path / "first", tmp_path / "gaps"
    assert sitl(["fly", *SMALL, "--p-traj", "35", "--out", str(run1), "-q"]) == 0
    assert ground(["report", str(run1), "--out", str(run1 / "report"), "--no-plots", "-q"]) == 0
    assert sitl(["fly", *SMALL, "--mission", "fill-gaps", "--fill-gaps", str(run1 / "report"), "--phase", "3",
                 "--out", str(run2), "-q"]) == 0
    assert ground(["report", str(run1), str(run2), "--out", str(tmp_path / "merged"), "--no-plots", "-q"]) == 0
    first = json.loads((run1 / "report" / "report.json").read_text())
    merged = json.loads((tmp_path / "merged" / "report.json").read_text())
    plan = json.loads((run2 / "truth.json").read_text())["mission"]["plan"]
    assert plan["kind"] == "fill-gaps" and plan["gap_cells"] > 0
    assert first["coverage_ratio_pct"] < 97.0  # the first flight left gaps
    seen_before = first["coverage_ratio_pct"]
    # most of what the first flight missed is seen now, as the model predicted (to a point)
    assert merged["coverage_ratio_pct"] - seen_before > 0.8 * (100.0 - seen_before)
    assert abs(merged["coverage_ratio_pct"] - plan["predicted_merged_ra_pct"]) < 1.0
    assert abs(merged["volume_error_pct"]) < abs(first["volume_error_pct"])
    assert len(merged["flights"]) == 2
