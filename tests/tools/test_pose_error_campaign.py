"""`python -m tools.pose_error_campaign`: what a drifting pose does to the volume when nothing corrects it."""

import json
import subprocess
from pathlib import Path

import pytest

from sitl.sensing.pose_drift import PoseErrorProfile
from tools import pose_error_campaign
from tools.pose_error_campaign import fly_and_report, main, table


@pytest.fixture
def fake_programs(monkeypatch):
    """The two programs replaced by stand-ins that write what they would (a truth.json, a report.json) and record
    their command lines: the table is about which report it reads, not about flying."""
    calls: list[list[str]] = []

    def run(argv, **_kw):
        calls.append(list(argv))
        out = Path(argv[argv.index("--out") + 1])
        out.mkdir(parents=True, exist_ok=True)
        if argv[2] == "sitl.cli":
            seed = int(argv[argv.index("--seed") + 1])
            stats = {} if "none" in argv else {"horizontal_rms_m": 0.5 + seed, "horizontal_max_m": 1.0,
                                               "vertical_rms_m": 0.1, "heading_rms_deg": 0.3}
            (out / "truth.json").write_text(json.dumps({"flight_time_s": 130.0, "pose_error": {"stats": stats}}))
        else:
            corrected = "--no-pose-correction" not in argv
            (out / "report.json").write_text(json.dumps({"volume_error_pct": 0.1 if corrected else 4.0,
                                                         "coverage_ratio_pct": 98.0}))
        return subprocess.CompletedProcess(argv, 0)

    monkeypatch.setattr(pose_error_campaign.subprocess, "run", run)
    return calls


def test_that_each_flight_is_reported_with_the_correction_off(tmp_path, fake_programs):
    """The correction is on by default; this table is what it has to undo, so its report must turn it off."""
    row = fly_and_report(PoseErrorProfile.VIO, 1, tmp_path)
    report_argv = next(a for a in fake_programs if "ground.cli" in a)
    assert "--no-pose-correction" in report_argv
    assert row["ve_pct"] == 4.0 and row["horizontal_rms_m"] == 1.5


def test_that_the_table_gives_each_flight_and_each_profiles_mean():
    rows = [{"profile": "vio", "seed": s, "ve_pct": v, "ra_pct": 98.0, "horizontal_rms_m": h, "horizontal_max_m": 1.0,
             "vertical_rms_m": 0.1, "heading_rms_deg": 0.3} for s, v, h in ((0, 1.0, 0.2), (1, 3.0, 0.4))]
    text = table(rows)
    assert "| vio | 0 | 0.20 | 1.00 | 0.10 | 0.30 | 1.00 | 98.0 |" in text
    assert "| **vio, mean** | 2 seeds | 0.30 | 1.00 | 0.10 | 0.30 | 2.00 | 98.0 |" in text


def test_that_write_replaces_only_its_section_and_says_the_report_was_uncorrected(tmp_path, fake_programs):
    page = tmp_path / "pose_error.md"
    page.write_text("before\n\n<!-- pose-error-table:start -->\nold\n<!-- pose-error-table:end -->\n\nafter\n")
    assert main(["--seeds", "0", "--keep", str(tmp_path / "runs"), "--write", str(page)]) == 0
    text = page.read_text()
    assert text.startswith("before\n") and text.rstrip().endswith("after") and "old" not in text
    assert "--no-pose-correction" in text
    assert sum("ground.cli" in a for a in fake_programs) == len(PoseErrorProfile)
