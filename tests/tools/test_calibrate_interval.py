"""tools.calibrate_interval: the fit reaches its coverage with the narrowest interval it can find."""

from __future__ import annotations

import math

import numpy as np

from ground.uncertainty import ErrorTerms, IntervalModel
from tools.calibrate_interval import (
    FACTORS,
    MODEL_BEGIN,
    MODEL_END,
    chance_of_so_few_pct,
    coverage,
    document,
    fit,
    model_of,
    readme_summary,
    write_model,
)


def _rows(n: int, seed: int) -> list[dict]:
    """Runs whose error is the noise term times a standard normal; the other terms are red herrings."""
    rng = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        noise = rng.uniform(5, 50)
        t = ErrorTerms(interpolation_m3=rng.uniform(0, 100), noise_m3=noise)
        truth = 1000.0
        rows.append({"run_id": str(i), "volume_m3": truth + noise * rng.normal(), "true_volume_m3": truth,
                     "floor_area_m2": 100.0, "split": "calibration", **t.as_dict()})
    return rows


def test_that_the_fitted_interval_covers_90_percent_of_its_runs_and_of_fresh_ones():
    k, _ = fit(_rows(400, 1), n_candidates=500)
    model = model_of(k, "test")
    assert coverage(model, _rows(400, 1))["coverage_pct"] >= 90.0
    assert 85.0 <= coverage(model, _rows(2000, 2))["coverage_pct"] <= 95.0
    # the noise term explains the error: its factor is near the normal's 90 % quantile, the others near zero
    assert model.k_noise > 1.3 and model.k_noise < 2.0
    assert model.k_interpolation < 0.3


def test_that_the_interval_holds_within_each_noise_model_not_only_on_average():
    # two sensors: one whose errors the noise term explains at twice the scale of the other's
    calm, rough = _rows(300, 3), _rows(100, 4)
    for r in calm:
        r["noise"] = "calm"
    for r in rough:
        r["noise"] = "rough"
        r["volume_m3"] = r["true_volume_m3"] + 2.0 * (r["volume_m3"] - r["true_volume_m3"])
    pooled = model_of(fit(calm + rough, n_candidates=300, stratum=None)[0], "pooled")
    per_model = model_of(fit(calm + rough, n_candidates=300, stratum="noise")[0], "per model")
    assert coverage(pooled, rough)["coverage_pct"] < 85.0  # the majority hides the rough sensor
    assert coverage(per_model, rough)["coverage_pct"] >= 90.0 and coverage(per_model, calm)["coverage_pct"] >= 90.0


def test_that_the_interval_holds_within_each_pile_family_except_those_a_height_map_cannot_hold():
    # one P_traj; a common family, a rarer one whose errors are twice the scale, and a box whose errors no term sees
    common, rare, box = _rows(300, 5), _rows(60, 6), _rows(20, 7)
    for family, rows in (("cone", common), ("wall", rare), ("box", box)):
        for r in rows:
            r["family"], r["p_traj_pct"] = family, 20
    for r in rare:
        r["volume_m3"] = r["true_volume_m3"] + 2.0 * (r["volume_m3"] - r["true_volume_m3"])
    for r in box:
        r["volume_m3"] = r["true_volume_m3"] + 200.0 * (1 if int(r["run_id"]) % 2 else -1)
    rows = common + rare + box
    by_ptraj = model_of(fit(rows, n_candidates=300, families=False)[0], "P_traj only")
    by_family = model_of(fit(rows, n_candidates=300)[0], "and families")
    assert coverage(by_ptraj, rare)["coverage_pct"] < 85.0  # the common family hides the rare one
    assert coverage(by_family, rare)["coverage_pct"] >= 90.0 and coverage(by_family, common)["coverage_pct"] >= 90.0
    # the box is not held to 90 %: that would take an interval of +-200 m3 on every pile
    assert coverage(by_family, box)["coverage_pct"] < 50.0
    assert coverage(by_family, common)["median_half_width_pct"] < 10.0


def test_that_the_fitted_model_is_written_between_its_markers(tmp_path):
    src = tmp_path / "u.py"
    src.write_text(f"x = 1\n{MODEL_BEGIN}\nold\n{MODEL_END}\ny = 2\n")
    model = IntervalModel(**dict.fromkeys(FACTORS, 0.5), source="fitted here")
    write_model(model, src)
    text = src.read_text()
    assert text.startswith("x = 1\n") and text.endswith("y = 2\n") and "old" not in text
    ns: dict = {"IntervalModel": IntervalModel}
    exec(text.split(MODEL_BEGIN)[1].split(MODEL_END)[0], ns)
    assert ns["DEFAULT_INTERVAL_MODEL"] == model


def test_that_the_readme_summary_states_the_held_out_figures_and_the_weakest_group():
    rows = _rows(200, 8)
    for i, r in enumerate(rows):
        r["p_traj_pct"], r["noise"], r["family"] = (5, 35)[i % 2], "none", "cone"
    model = model_of(fit(rows, n_candidates=200)[0], "test")
    c = coverage(model, rows)
    worst, at = min((coverage(model, [r for r in rows if r["p_traj_pct"] == p])["coverage_pct"], p) for p in (5, 35))
    text = readme_summary(model, rows)
    assert f"{c['coverage_pct']:.1f} % of 200 surveys" in text and f"±{c['median_half_width_pct']:.2f} %" in text
    assert f"the lowest: {worst:.1f} % at P_traj {at} %" in text and "on cone piles" in text
    assert "P_traj 5 %" in text and "at 35 %" in text


def test_that_the_piles_a_height_map_cannot_hold_take_no_part_in_the_fit():
    common, box = _rows(200, 9), _rows(30, 10)
    for r in box:
        r["family"] = "box"
        r["volume_m3"] = r["true_volume_m3"] + 300.0  # an error no term sees
    alone = fit(common, n_candidates=100)[0]
    assert np.allclose(fit(common + box, n_candidates=100)[0], alone)


def test_that_the_chance_of_so_few_inside_tells_a_small_group_s_draw_from_a_defect():
    """88.9 % of 63 surveys is as likely as not from a 90 % interval; 80 % of 63, or 88.9 % of 6,300, is not."""
    assert 40.0 < chance_of_so_few_pct(56, 63) < 50.0
    assert chance_of_so_few_pct(50, 63) < 1.0
    assert chance_of_so_few_pct(5600, 6300) < 1.0
    assert chance_of_so_few_pct(63, 63) == 100.0 and math.isnan(chance_of_so_few_pct(0, 0))
    rows = _rows(200, 8)
    for r in rows:
        r["p_traj_pct"], r["noise"], r["family"], r["building"] = 20, "none", "cone", "paper"
    model = model_of(fit(rows, n_candidates=200)[0], "test")
    c = coverage(model, rows)
    inside = round(c["coverage_pct"] * c["n"] / 100.0)
    assert c["chance_pct"] == chance_of_so_few_pct(inside, c["n"])
    text = document(model, rows, rows, "cmd")
    assert f"| {c['chance_pct']:.0f} % |" in text and "chance of so few" in text
