"""The survey's metadata (who, where, when, the log's checksum), the verdict line, and the report with piles
as a user runs it: --config with [site] name/timezone, [survey] and [[piles]], --density and the units."""

from __future__ import annotations

import csv
import hashlib
import json
from dataclasses import fields
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.cli import ExitCode
from firmware_py.core.storage import Storage
from ground.cli import main
from ground.metadata import SurveyInfo, limiting_terms, metadata_rows, remedies, survey_metadata, verdict
from ground.uncertainty import DEFAULT_INTERVAL_MODEL, ErrorTerms
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly


def a_log(tmp_path: Path) -> Path:
    p = tmp_path / "samples.pslog"
    p.write_bytes(b"not really a log, but bytes to hash")
    return p


def test_that_local_time_comes_from_the_sites_time_zone(tmp_path):
    header = {"created_utc": "2026-07-01T09:30:00+00:00", "sensor": {"model": "Garmin LIDAR-Lite v3"},
              "software": "pilescan 0.1.0"}
    meta, warnings = survey_metadata(header, SurveyInfo(timezone="America/Chicago"), a_log(tmp_path),
                                     np.array([10.0, 70.0, 130.0]))
    assert warnings == []
    assert meta["survey_start_utc"] == "2026-07-01T09:30:00+00:00"
    assert meta["survey_start_local"] == "2026-07-01T04:30:00-05:00"  # CDT in July
    assert meta["survey_duration_s"] == 120.0
    assert meta["sensor"] == "Garmin LIDAR-Lite v3" and meta["flight_software"] == "pilescan 0.1.0"


def test_that_without_a_time_zone_the_report_says_utc_only(tmp_path):
    meta, _ = survey_metadata({"created_utc": "2026-07-01T09:30:00+00:00"}, SurveyInfo(), a_log(tmp_path))
    assert meta["survey_start_local"] is None and meta["timezone"] is None
    assert dict(metadata_rows(meta))["Survey start (local)"].startswith("UTC only")
    assert dict(metadata_rows(meta))["Operator"] == "not stated"


def test_that_the_checksum_is_the_sha256_of_the_log_file(tmp_path):
    log = a_log(tmp_path)
    meta, _ = survey_metadata({}, SurveyInfo(), log)
    assert meta["log_sha256"] == hashlib.sha256(log.read_bytes()).hexdigest()


def test_that_the_logged_configuration_fills_what_the_report_is_not_told(tmp_path):
    header = {"config": {"site": {"name": "Bay 3", "timezone": "Europe/Paris"},
                         "survey": {"operator": "A. Pilot", "aircraft": "X8"}}}
    meta, _ = survey_metadata(header, SurveyInfo(operator="B. Surveyor"), a_log(tmp_path))
    assert (meta["site_name"], meta["operator"], meta["aircraft"], meta["timezone"]) == \
        ("Bay 3", "B. Surveyor", "X8", "Europe/Paris")


@pytest.mark.parametrize("header", [{"created_utc": "yesterday"}, {"created_utc": "2026-07-01T09:30:00"},
                                    {"config": {"site": {"timezone": "Nowhere/Land"}}}])
def test_that_a_malformed_time_or_zone_in_the_log_is_a_warning_not_a_failure(tmp_path, header):
    meta, warnings = survey_metadata(header, SurveyInfo(), a_log(tmp_path))
    assert len(warnings) == 1 and meta["survey_start_local"] is None


def test_that_a_bad_time_zone_given_to_the_report_is_refused():
    with pytest.raises(ValueError, match="not a time zone"):
        SurveyInfo(timezone="Mars/Olympus_Mons")


def test_that_the_verdict_names_the_interval_and_what_limits_it():
    t = ErrorTerms(unseen_low_m3=400.0, unseen_high_m3=400.0, interpolation_m3=1.0)
    limits = limiting_terms(t, DEFAULT_INTERVAL_MODEL)
    assert limits == ["unseen"]
    line = verdict(7210.4, (7160.2, 7250.9), limits, "x 0-9 m, y 0-40 m", 2)
    assert line == ("7,210 m³ (90 % interval 7,160–7,251 m³); limited by: ground the survey never saw near "
                    "x 0-9 m, y 0-40 m; 2 warnings to read")
    assert verdict(10.0, None, [], None, 0).endswith("(no interval: the survey's errors could not be estimated)")
    assert verdict(764.555, (764.555, 764.555), [], None, 0, "yd³", 0.9144**3).startswith("1,000 yd³")
    pose = limiting_terms(ErrorTerms(interpolation_m3=1.0, pose_m3=400.0), DEFAULT_INTERVAL_MODEL)
    assert pose == ["pose"]  # a corrected height's error that holds the interval is named
    assert "the height of the drifting pose" in verdict(7210.4, (6800.0, 7600.0), pose, None, 0)
    # a survey with another reading the data cannot rule out says it in the same sentence, in the display unit
    other = {"condition": "the floor seen only away from the walls is a hollow in the pile", "volume_m3": 1143.2,
             "volume_interval_m3": [1012.4, 1273.9]}
    line = verdict(1037.4, (1020.6, 1054.2), pose, None, 3, other=other)
    assert line == ("1,037 m³ (90 % interval 1,021–1,054 m³); limited by: the height of the drifting pose, as "
                    "corrected from the building; or 1,143 m³ (90 % interval 1,012–1,274 m³) if the floor seen only "
                    "away from the walls is a hollow in the pile; 3 warnings to read")
    assert "or 1,495 yd³ (" in verdict(1037.4, (1020.6, 1054.2), [], None, 0, "yd³", 0.9144**3, other)
    level = limiting_terms(ErrorTerms(interpolation_m3=1.0, level_m3=100.0), DEFAULT_INTERVAL_MODEL)
    assert level == ["level"]  # a level no floor pinned, when it holds the interval, is named
    assert "the drifting altitude reference, which no floor seen pinned" in verdict(1200.0, (1000.0, 1400.0), level,
                                                                                     None, 0)
    untied = limiting_terms(ErrorTerms(interpolation_m3=1.0, untied_m3=100.0), DEFAULT_INTERVAL_MODEL)
    assert untied == ["untied"]  # and so are the stretches no floor tied
    assert "over stretches of the flight no floor seen tied" in verdict(1200.0, (1000.0, 1400.0), untied, None, 0)



def test_that_every_term_a_verdict_can_name_has_its_meaning_and_remedy_in_the_interval_page():
    # a surveyor reads "limited by: ..." and looks it up: a term added without its row would be a verdict unexplained
    from ground.metadata import _LIMITS, _REMEDIES
    page = (Path(__file__).resolve().parents[2] / "docs" / "uncertainty.md").read_text()
    rows = {cells[0].removesuffix(" (near ...)"): cells for cells in (
        line.strip("| ").split(" | ") for line in page.splitlines() if line.startswith("| "))}
    missing = [words for words in _LIMITS.values() if words not in rows]
    assert not missing, missing
    # and the remedy it gives is the one the report prints under the verdict
    assert all(rows[_LIMITS[k]][-1] == _REMEDIES[k] for k in _LIMITS), [rows[w][-1] for w in _LIMITS.values()]
    assert set(_LIMITS) == {f.name.removesuffix("_m3").removesuffix("_low").removesuffix("_high")
                            for f in fields(ErrorTerms)} | {"fitted_floor", "earlier_survey"}  # one phrase a term,
    # and one for each base that brings its own error (ground.base)


def test_that_a_base_that_holds_the_interval_is_named_in_the_verdict():
    terms = ErrorTerms(interpolation_m3=10.0)
    assert limiting_terms(terms, DEFAULT_INTERVAL_MODEL, ("fitted_floor", 100.0)) == ["fitted_floor"]
    interp = DEFAULT_INTERVAL_MODEL.k_interpolation * 10.0  # the interpolation term as the fitted factor scales it
    both = limiting_terms(terms, DEFAULT_INTERVAL_MODEL, ("earlier_survey", 1.2 * interp))
    assert both == ["earlier_survey", "interpolation"]
    assert limiting_terms(terms, DEFAULT_INTERVAL_MODEL, ("fitted_floor", 0.1)) == ["interpolation"]

# ----- the report, as a user runs it -------------------------------------------------------------------------


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("run")
    # The paper's pile 1 in the small building, batch payload: what is read is the metadata, not the survey.
    fly(FlyConfig(mission=Mission(storage=Storage(30, 20, 10), altitude_m=9.0, p_traj=0.2)), out, force=True)
    return out


def test_that_the_report_carries_metadata_verdict_and_piles(run_dir, tmp_path, capsys):
    cfg = tmp_path / "site.toml"
    cfg.write_text('[site]\nname = "Paper bay"\ntimezone = "Asia/Tokyo"\n[survey]\noperator = "J. Smith"\n'
                   '[[piles]]\nname = "ore"\nx_m = 15\ny_m = 10\ndensity_kg_m3 = 2500\n'
                   '[[piles]]\nname = "gone"\nx_m = 1\ny_m = 1\n')
    out = tmp_path / "r"
    assert main(["report", str(run_dir), "--out", str(out), "--no-plots", "--config", str(cfg),
                 "--volume-units", "yd3", "--mass-units", "short-ton"]) == 0
    printed = capsys.readouterr().out
    rep = json.loads((out / "report.json").read_text())
    meta = rep["metadata"]
    assert meta["site_name"] == "Paper bay" and meta["operator"] == "J. Smith"
    assert meta["survey_start_local"].endswith("+09:00")
    assert meta["log_sha256"] == hashlib.sha256((run_dir / "samples.pslog").read_bytes()).hexdigest()
    piles = rep["piles"]["piles"]
    ore = next(p for p in piles if p["label"] == "ore")
    assert ore["mass_kg"] == pytest.approx(ore["volume_m3"] * 2500)
    assert ore["display"]["volume_unit"] == "yd3"
    assert any("'gone'" in w for w in rep["warnings"])
    assert rep["piles"]["volume_in_piles_m3"] + rep["piles"]["volume_outside_piles_m3"] == \
        pytest.approx(rep["volume_m3"], rel=1e-9)
    assert "verdict" in printed and "yd³" in rep["verdict"] and "ore" in printed
    with (out / "piles.csv").open(newline="", encoding="utf-8") as f:
        rows = list(csv.DictReader(f))
    assert [r["label"] for r in rows] == [p["label"] for p in piles]
    html = (out / "report.html").read_text()
    assert "Paper bay" in html and "<h2>Piles</h2>" in html and "Verdict:" in html
    # under the verdict, what would narrow the interval: one line for each term it names, in its order
    limits = limiting_terms(ErrorTerms(**rep["interval_terms_m3"]), DEFAULT_INTERVAL_MODEL)
    assert limits and rep["to_narrow_interval"] == remedies(limits)
    assert "To narrow the interval:" in html and "to narrow it" in printed
    assert "To narrow the interval:" in (out / "report.md").read_text()


def test_that_a_real_survey_shows_no_truth_rows(run_dir, tmp_path):
    log_only = tmp_path / "samples.pslog"  # a bare log: no truth.json beside it
    log_only.write_bytes((run_dir / "samples.pslog").read_bytes())
    out = tmp_path / "r"
    assert main(["report", str(log_only), "--out", str(out), "--no-plots", "-q"]) == 0
    for name in ("report.md", "report.html"):
        text = (out / name).read_text()
        assert "True volume (reference)" not in text and "Volume error Ve" not in text


@pytest.mark.parametrize(("args", "match"), [
    (["--density", "-5"], "density must be in (0, 22600] kg/m³"),
    (["--timezone", "Mars/Olympus_Mons"], "not a time zone"),
    (["--volume-units", "litres"], "invalid choice"),
    (["--min-pile-area", "-1"], "least pile area"),
])
def test_that_bad_pile_and_metadata_options_are_one_line(run_dir, tmp_path, capsys, args, match):
    code = main(["report", str(run_dir), "--out", str(tmp_path / "r"), "--no-plots", *args])
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE, err
    assert err.count("\n") == 1 and "Traceback" not in err and match in err
    assert not (tmp_path / "r").exists()
