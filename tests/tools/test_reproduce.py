"""The reproduction command on a tiny grid: cases, cache, rows, Table 2, trends, figures (seconds)."""

import pytest

from ground.surface import DEFAULT_EMPTY_CELLS
from tools.experiments import ALL_EXPERIMENTS, Experiment, cases_for, load_experiments, servo_positions
from tools.reproduce import main
from tools.sweep import read_rows_csv

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)


def test_that_a_tiny_sweep_writes_rows_table_2_and_figures_and_reruns_from_its_cache(tmp_path, capsys):
    args = ["--experiments", "baseline,sinusoidal,2d,baseline-ideal", "--piles", "1", "--p-traj", "25",
            "--positions", "1", "--jobs", "1", "--cache", str(tmp_path / "cache"), "--rows", str(tmp_path / "rows.csv"),
            "--write", str(tmp_path / "docs" / "results.md"), "--quiet"]
    assert main(args) == 0
    rows = read_rows_csv(tmp_path / "rows.csv")
    assert len(rows) == 4  # one servo position for each 1D run (servo_positions: the grid's test), one 2D scan
    assert {r["group"] for r in rows} == {"baseline", "sinusoidal", "2d", "baseline-ideal"}
    assert all(r["energy_j"] is None for r in rows if r["group"] == "baseline-ideal")
    assert all(0 <= r["ve_nearest_pct"] < 5 and 80 < r["ra_pct"] <= 100 for r in rows)
    md = (tmp_path / "docs" / "results.md").read_text()
    assert "| Actuated 1D LiDAR (baseline) | 1 |" in md and "| 2D LiDAR (Hokuyo UTM-30LX) | 1 |" in md
    assert "sinusoidal ≈ semi-triangular" in md
    assert (tmp_path / "docs" / "figures" / "fig13_waveform.png").is_file()
    cached = sorted((tmp_path / "cache" / "cases").glob("*.json"))
    assert len(cached) == 4
    mtimes = [p.stat().st_mtime_ns for p in cached]
    assert main(args) == 0  # everything from the cache
    assert [p.stat().st_mtime_ns for p in cached] == mtimes
    assert read_rows_csv(tmp_path / "rows.csv") == rows


def test_that_cases_cover_the_grid_and_change_key_with_the_configuration():
    base = ALL_EXPERIMENTS["baseline"]
    cases = cases_for([base, ALL_EXPERIMENTS["yaw-6"]], ("1", "2"), (5, 30))
    assert len(cases) == 8 and len({c.key for c in cases}) == 8
    slower = Experiment("baseline", yaw_rate_max_dps=29.0)
    assert cases_for([slower], ("1",), (5,))[0].key != cases_for([base], ("1",), (5,))[0].key
    assert servo_positions(20) == list(range(20)) and servo_positions(2) == [0, 10]


def test_that_experiments_load_from_toml_and_bad_ones_are_refused(tmp_path):
    good = tmp_path / "good.toml"
    good.write_text('[[experiment]]\nname = "yaw-6"\nyaw_rate_max_dps = 6\n\n'
                    '[[experiment]]\nname = "fast"\nspeed_m_s = 2\n')
    assert [e.name for e in load_experiments(good)] == ["yaw-6", "fast"]
    for text, words in [('[[experiment]]\nname = "x"\nwarp = 9\n', "unknown experiment field"),
                        ('[[experiment]]\nname = "x"\nsensor = "radar"\n', "sensor"),
                        ('[[experiment]]\nname = "x"\nspeed_m_s = -1\n', "speed"),
                        ("name = 1\n", "[[experiment]]"), ("[[experiment\n", "cannot read")]:
        bad = tmp_path / "bad.toml"
        bad.write_text(text)
        with pytest.raises(ValueError, match=words.replace("[", r"\[")):
            load_experiments(bad)


@pytest.mark.parametrize(("argv", "words"), [
    (["--experiments", "warp"], "unknown experiment"),
    (["--p-traj", "60"], "--p-traj"),
    (["--positions", "0"], "servo positions"),
    (["--jobs", "0"], "--jobs"),
])
def test_that_bad_options_fail_in_one_line(tmp_path, capsys, argv, words):
    assert main([*argv, "--cache", str(tmp_path / "c"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and words in err and "Traceback" not in err


def test_that_a_noise_experiment_draws_per_position_and_logs_the_draws(tmp_path):
    cfg = tmp_path / "noise.toml"
    cfg.write_text('[[experiment]]\nname = "noise"\nnoise_draws = 2\n')
    assert main(["--config", str(cfg), "--piles", "1", "--p-traj", "25", "--positions", "1", "--jobs", "1",
                 "--cache", str(tmp_path / "cache"), "--rows", str(tmp_path / "rows.csv"), "--quiet"]) == 0
    rows = read_rows_csv(tmp_path / "rows.csv")
    assert [r["draw"] for r in rows] == [0, 1]
    assert rows[0]["ve_nearest_pct"] != rows[1]["ve_nearest_pct"]  # two different noise draws


def test_that_the_noise_summary_goes_into_the_readmes_section_with_each_rows_verdict(tmp_path):
    cfg = tmp_path / "noise.toml"
    cfg.write_text('[[experiment]]\nname = "baseline"\n\n[[experiment]]\nname = "noise"\nnoise_draws = 1\n')
    readme = tmp_path / "README.md"
    readme.write_text("# A page\n\nIts own text.\n")
    assert main(["--config", str(cfg), "--piles", "1", "--p-traj", "25", "--positions", "1", "--jobs", "1",
                 "--cache", str(tmp_path / "cache"), "--rows", str(tmp_path / "rows.csv"), "--quiet",
                 "--readme", str(readme)]) == 0
    text = readme.read_text()
    assert text.startswith("# A page\n\nIts own text.\n")
    section = text[text.index("<!-- reproduce-noise:start -->"):text.index("<!-- reproduce-noise:end -->")]
    rows = read_rows_csv(tmp_path / "rows.csv")
    clean = next(r for r in rows if r["group"] == "baseline")[f"ve_{DEFAULT_EMPTY_CELLS}_pct"]
    noisy = next(r for r in rows if r["group"] == "noise")[f"ve_{DEFAULT_EMPTY_CELLS}_pct"]
    verdict = "yes" if abs(noisy - clean) <= 0.2 else "no"
    assert f"| 1 | 25 % | {clean:.2f} | {noisy:.2f} ± 0.00 | {noisy - clean:+.2f} | {verdict} |" in section
    assert ("in 1 of 1 rows" if verdict == "yes" else "not for pile 1 at 25 %") in section


def test_that_a_readme_that_is_not_a_page_is_refused_before_the_sweep(tmp_path, capsys):
    assert main(["--experiments", "baseline", "--readme", str(tmp_path / "missing.md"), "--cache",
                 str(tmp_path / "c"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "--readme" in err and not (tmp_path / "c").exists()
