"""Report rendering: Markdown numbers and warnings, self-contained escaped HTML, PLY round trip."""

from __future__ import annotations

import base64
import re

import matplotlib.image as mpimg
import numpy as np
import pytest
import trimesh
from matplotlib import colormaps

from ground import render

XSS = "<script>alert('x')</script>"


def full_report() -> dict:
    return {
        "volume_m3": 12345.678,
        "true_volume_m3": 12000.0,
        "volume_error_pct": 2.8806,
        "coverage_ratio_pct": 85.4,
        "n_samples": np.int64(123456),
        "n_points_used": 100000,
        "n_points_removed_walls": 2345,
        "cell_size_m": 0.25,
        "empty_cell_policy": "leave",
        "surface_fit": "cubic-limited",
        "storage": {"length_m": 60.0, "width_m": 30.0, "height_m": 12.0},
        "log": {"blocks_ok": 1200, "blocks_corrupt": 2, "blocks_truncated": 1, "bytes_skipped": 77},
        "source": "runs/demo",
        "software_version": "pilescan 0.1.0",
        "elapsed_s": 3.14159,
        "warnings": ["sample log damaged: 2 corrupt block(s)", f"odd input {XSS}"],
        "mission_id": "m-42",
        "fit": {"rmse_m": 0.0123, "detail": {"n_triangles": 4567}},
        "uncovered_area_m2": 262.5,
    }


@pytest.fixture
def images(tmp_path):
    out = {}
    rng = np.random.default_rng(0)
    for name in ("cloud", "height_map", "coverage"):
        p = tmp_path / f"{name}.png"
        mpimg.imsave(p, rng.random((8, 12)))
        out[name] = p
    return out


# ---------------------------------------------------------------------------------------- format


def test_number_formats():
    assert render.fmt_volume(1234567.89) == "1,234,567.9 m³"
    assert render.fmt_volume(None) == render.UNKNOWN == "unknown"
    assert render.fmt_pct(1.23456) == "1.23 %"
    assert render.fmt_count(np.int64(1234567)) == "1,234,567"
    assert render.fmt_value(np.float64(0.000123456789)) == "0.000123457"
    assert render.fmt_value(True) == "yes"
    assert render.fmt_value(list(range(100))) == "[100 items]"
    assert render.fmt_volume(float("nan")) == "nan"


def test_flatten_nested_dicts():
    flat = render.flatten({"a": 1, "b": {"c": 2, "d": {"e": 3}}, "f": {}})
    assert flat == [("a", 1), ("b.c", 2), ("b.d.e", 3), ("f", "{}")]


# -------------------------------------------------------------------------------------- markdown


def test_markdown_contains_numbers_warnings_images_and_method(tmp_path, images):
    out = render.write_markdown(full_report(), images, tmp_path / "report.md")
    assert out == tmp_path / "report.md"
    md = out.read_text(encoding="utf-8")
    assert md.startswith("# pilescan volume report\n")
    for expected in [
        "12,345.7 m³", "12,000.0 m³", "2.88 %", "85.40 %", "123,456", "100,000", "2,345",
        "0.250 m", "leave", "60.00 m × 30.00 m × 12.00 m", "1,200 ok, 2 corrupt, 1 truncated",
        "runs/demo", "pilescan 0.1.0", "3.14 s",
    ]:
        assert expected in md, expected
    # Warnings come before the summary and are listed one per line.
    assert md.index("## Warnings") < md.index("## Summary")
    assert "> - sample log damaged: 2 corrupt block(s)" in md
    assert "2 warnings" in md
    assert "<script>" not in md  # neutralised for viewers that render inline HTML
    # Images by relative file name.
    for name in ("cloud.png", "height_map.png", "coverage.png"):
        assert f"]({name})" in md
    assert "## Method" in md and "Clough-Tocher" in md and "eq. 9" in md
    # Other top-level keys, nested ones dotted; headline keys are not repeated there.
    extra = md[md.index("## All figures"):]
    for expected in ["| mission_id | m-42 |", "| fit.rmse_m | 0.0123 |", "| fit.detail.n_triangles | 4,567 |",
                     "| uncovered_area_m2 | 262.5 |", "| log.bytes_skipped | 77 |"]:
        assert expected in extra, expected
    assert "volume_m3" not in extra and "log.blocks_ok" not in extra and "storage." not in extra


def test_markdown_images_in_subdirectory_are_relative(tmp_path):
    sub = tmp_path / "figs"
    sub.mkdir()
    mpimg.imsave(sub / "a b.png", np.zeros((4, 4)))
    md = render.write_markdown({}, {"cloud": sub / "a b.png"}, tmp_path / "report.md").read_text()
    assert "](figs/a%20b.png)" in md
    assert str(tmp_path) not in md


def test_markdown_missing_values_and_no_warnings(tmp_path):
    md = render.write_markdown({"volume_m3": None, "warnings": []}, {}, tmp_path / "r.md").read_text()
    assert "No warnings." in md
    assert "| Stockpile volume | unknown |" in md
    assert md.count("unknown") >= len(render.SUMMARY_KEYS) - len(render.REFERENCE_KEYS) - len(render.OPTIONAL_KEYS)
    assert "## All figures" not in md and "## Figures" not in md


def test_that_without_a_reference_volume_there_are_no_truth_or_ve_rows(tmp_path):
    rep = {"volume_m3": 12.0, "true_volume_m3": None, "volume_error_pct": None, "volume_error_m3": None,
           "truth_in_interval": None, "warnings": []}
    for text in (render.write_markdown(rep, {}, tmp_path / "r.md").read_text(),
                 render.write_html(rep, {}, tmp_path / "r.html").read_text()):
        assert "True volume (reference)" not in text and "Volume error Ve" not in text and "volume_error" not in text
        assert "truth_in_interval" not in text
    with_truth = render.write_markdown({**rep, "true_volume_m3": 10.0, "volume_error_pct": 20.0}, {},
                                       tmp_path / "t.md").read_text()
    assert "| True volume (reference) | 10.0 m³ |" in with_truth
    assert "| Volume error Ve (eq. 8) | 20.00 % |" in with_truth


def test_markdown_escapes_table_breaking_text(tmp_path):
    md = render.write_markdown({"source": "a|b\nc"}, None, tmp_path / "r.md").read_text()
    assert "| Source | a\\|b c |" in md


# ------------------------------------------------------------------------------------------ html


def test_html_is_self_contained_and_escaped(tmp_path, images):
    out = render.write_html(full_report(), images, tmp_path / "report.html")
    page = out.read_text(encoding="utf-8")
    assert page.startswith("<!DOCTYPE html>")
    assert "http://" not in page and "https://" not in page
    assert "<link" not in page and "@import" not in page
    assert re.findall(r"<script[^>]*>", page) == ["<script>"]  # one inline script (the image check), no src
    assert "fetch(" not in page and "XMLHttpRequest" not in page
    srcs = re.findall(r'src="([^"]*)"', page)
    assert len(srcs) == 3
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    # Inlined bytes are exactly the PNG files, in the given order.
    for src, path in zip(srcs, images.values(), strict=True):
        assert base64.b64decode(src.split(",", 1)[1]) == path.read_bytes()
    assert "&lt;script&gt;alert(&#x27;x&#x27;)&lt;/script&gt;" in page
    assert 'class="warnings"' in page
    assert "sample log damaged: 2 corrupt block(s)" in page
    for expected in ["12,345.7 m³", "2.88 %", "85.40 %", "fit.detail.n_triangles", "Clough-Tocher"]:
        assert expected in page, expected


def test_html_escapes_keys_and_values_everywhere(tmp_path):
    rep = {"source": "<b>bold</b>", "<k>": {"x&y": '"quoted"'}}
    page = render.write_html(rep, {"<img>": tmp_path / "missing.png"}, tmp_path / "r.html").read_text()
    assert "<b>" not in page and "<k>" not in page and "<img>" not in page
    assert "&lt;b&gt;bold&lt;/b&gt;" in page
    assert "&lt;k&gt;.x&amp;y" in page and "&quot;quoted&quot;" in page
    assert "Image not found" in page and "src=" not in page


LONG_WARNING = ("pose corrected from the building: horizontal 0.14 m RMS (0.20 max; over time); the floor and walls "
                "now 0.5 cm off their planes; 1252 of 1354 floor points dropped (a flat pile top); the heading from "
                f"the pile seen twice {XSS}")


def test_that_a_warning_of_many_clauses_is_its_headline_with_the_rest_listed_under_it(tmp_path):
    head, more = render.warning_parts(LONG_WARNING)
    assert head == "pose corrected from the building: horizontal 0.14 m RMS (0.20 max; over time)"  # not split in ()
    assert more[0] == "the floor and walls now 0.5 cm off their planes" and len(more) == 3
    assert render.warning_parts("a short one; with a reason") == ("a short one; with a reason", [])
    rep = {"warnings": [LONG_WARNING, "sample log damaged: 2 corrupt block(s)"]}
    page = render.write_html(rep, None, tmp_path / "r.html").read_text()
    assert f"<li>{head}<ul><li>{more[0]}</li>" in page and "<li>sample log damaged: 2 corrupt block(s)</li>" in page
    assert XSS not in page and "&lt;script&gt;" in page  # the clauses are escaped as the whole was
    md = render.write_markdown(rep, None, tmp_path / "r.md").read_text()
    assert f"> - {head}\n>   - {more[0]}\n" in md and "> - sample log damaged" in md


def test_html_without_warnings_or_data(tmp_path):
    page = render.write_html({}, None, tmp_path / "r.html").read_text()
    assert 'class="warnings"' not in page and "No warnings." in page
    assert "unknown" in page


# ------------------------------------------------------------------------------------------- ply


def test_ply_round_trip_with_height_colours(tmp_path):
    rng = np.random.default_rng(1)
    pts = rng.uniform([0, 0, 0], [60, 30, 8], size=(1000, 3))
    pts[5] = pts[6]  # duplicates are kept: a cloud, not a mesh
    out = render.write_ply(pts, tmp_path / "cloud.ply")
    assert out.read_bytes().startswith(b"ply\nformat binary_little_endian")
    back = trimesh.load(out)
    assert len(back.vertices) == len(pts)
    np.testing.assert_allclose(back.vertices, pts.astype(np.float32), rtol=0, atol=1e-5)
    colors = np.asarray(back.colors)
    top = np.array(colormaps["viridis"](1.0, bytes=True))
    assert np.array_equal(colors[np.argmax(pts[:, 2])], top)


def test_ply_without_colours(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    out = render.write_ply(pts, tmp_path / "c.ply", heights_as_color=False)
    header = out.read_bytes().split(b"end_header")[0]
    assert b"element vertex 2" in header and b"red" not in header
    np.testing.assert_allclose(trimesh.load(out).vertices, pts)


def test_ply_drops_non_finite_rows(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [np.nan, 0.0, 0.0], [4.0, 5.0, np.inf]])
    back = trimesh.load(render.write_ply(pts, tmp_path / "c.ply"))
    np.testing.assert_allclose(back.vertices, pts[:1])


@pytest.mark.parametrize("with_color", [True, False])
def test_ply_empty_cloud_is_valid(tmp_path, with_color):
    out = render.write_ply(np.empty((0, 3)), tmp_path / "e.ply", heights_as_color=with_color)
    data = out.read_bytes()
    assert data.startswith(b"ply\nformat binary_little_endian 1.0\n")
    assert b"element vertex 0\n" in data and data.endswith(b"end_header\n")
    assert (b"property uchar red" in data) == with_color
    loaded = trimesh.load(out)  # must not raise; trimesh returns an empty scene
    assert len(getattr(loaded, "vertices", [])) == 0


def test_ply_rejects_wrong_shape(tmp_path):
    with pytest.raises(ValueError, match=r"\(N, 3\)"):
        render.write_ply(np.zeros((4, 2)), tmp_path / "bad.ply")


def test_that_the_headline_gives_the_volume_in_the_chosen_unit_and_in_cubic_metres():
    from ground.render import headline
    rep = {"volume_m3": 764.555, "volume_interval_m3": [700.0, 800.0], "volume_unit": "yd3"}
    text = headline(rep)
    assert text.startswith("Stockpile volume: 1,000.0 yd³") and "764.6 m³" in text and "yd³)" in text
    assert headline({**rep, "volume_unit": "m3"}) == "Stockpile volume: 764.6 m³ (90 % interval 700.0 – 800.0 m³)"


def test_that_the_headline_says_a_change_over_an_earlier_survey_and_the_base_of_a_fitted_floor():
    # over an earlier survey the headline's number is the change: "Stockpile volume: 1,473.2 m³" read as the stock
    from ground.render import headline
    rep = {"volume_m3": 1473.2, "volume_interval_m3": [1400.0, 1550.0], "volume_unit": "m3"}
    assert headline({**rep, "base": {"kind": "survey"}}).startswith("Change since the earlier survey: 1,473.2 m³")
    assert headline({**rep, "base": {"kind": "fitted-floor"}}).startswith("Stockpile volume over the fitted floor:")
    assert headline({**rep, "base": {"kind": "floor"}}).startswith("Stockpile volume: 1,473.2 m³")
    yd = headline({**rep, "volume_unit": "yd3", "base": {"kind": "survey"}})
    assert yd.startswith("Change since the earlier survey: 1,926.9 yd³") and "; 1,473.2 m³" in yd


def test_that_the_method_paragraph_names_the_surface_fit_the_report_used():
    from ground.render import METHOD_TEXT, method_text

    assert "local plane" in method_text("local-linear") and "local plane" not in METHOD_TEXT
    assert "local plane" not in method_text("cubic-limited") and "Delaunay" in method_text("cubic-limited")
    plain, fixed = method_text("local-linear"), method_text("local-linear", noise_corrections=True, pointing_bias=True)
    assert "quadratic" not in plain and "quadratic" in fixed and "behind the surface" in fixed
    assert "piecewise-planar" in method_text("linear")
    assert "Gaussian process" in method_text("local-linear", "gp")
    bridges = method_text("local-linear", "gp-bridges")
    assert "Gaussian process" in bridges and "further than the smoothing reached" in bridges
    assert "Gaussian process" not in method_text("local-linear", "curvature") + method_text("cubic-limited", "gp")
    assert method_text("spline") == METHOD_TEXT and "Delaunay" not in METHOD_TEXT  # unnamed: no method claimed


def test_that_the_trajectory_correction_figure_is_an_engineers_figure_with_a_caption_that_says_what_it_shows(
        tmp_path, images):
    from ground.correction_plot import FIGURE_NAME
    p = tmp_path / f"{FIGURE_NAME}.png"
    mpimg.imsave(p, np.zeros((8, 12)))
    page = render.write_html(full_report(), {**images, FIGURE_NAME: p}, tmp_path / "report.html").read_text()
    caption = "Trajectory correction over time: what the report added to the autopilot&#x27;s logged position"
    assert caption in page
    assert FIGURE_NAME not in render.PAGE_IMAGES  # among the processing figures, not the customer's page
    assert page.index(caption) > page.index(render.ENGINEER_NOTE[:40].replace("'", "&#x27;"))


def test_that_the_engineers_part_is_named_once_in_the_html_and_leads_its_note_in_the_markdown(tmp_path, images):
    """Under its heading the page said "Engineer's details" twice in a row (the heading, then a note led by it)."""
    page = render.write_html(full_report(), images, tmp_path / "report.html").read_text()
    assert page.count("Engineer&#x27;s details") == 1
    assert "<p>The survey&#x27;s processing figures" in page
    md = render.write_markdown(full_report(), images, tmp_path / "report.md").read_text()
    assert "*Engineer's details: the survey's processing figures" in md


def test_that_a_value_that_rounds_to_zero_is_shown_without_a_minus_sign():
    """-0.04 m³ shown as '-0.0 m³' reads as a negative volume; the sign below the last digit shown is noise. A
    value that shows a digit keeps its sign."""
    from ground.render import fmt_pct, fmt_volume, signless_zero
    assert fmt_volume(-0.04) == "0.0 m³" and fmt_volume(-0.06) == "-0.1 m³" and fmt_volume(-0.0) == "0.0 m³"
    assert fmt_pct(-0.004) == "0.00 %" and fmt_pct(-0.006) == "-0.01 %"
    assert f"{signless_zero(-0.01, '+12,.1f'):+12,.1f}" == "        +0.0"  # the column keeps its width
    assert signless_zero(-0.001, ".0%") == 0.0 and signless_zero(-0.01, ".0%") == -0.01  # -1 % shows a digit
    assert signless_zero(-0.4, "d") == -0.4  # not a fixed-point spec: left alone


def test_that_comparing_a_survey_with_itself_shows_no_negative_zero():
    from ground.compare import format_change
    from ground.pile_change import format_pile_changes
    rec = {"net_m3": -0.0, "net_interval_m3": [-0.02, 0.02], "cut_m3": -0.0, "cut_interval_m3": [0.0, 0.0],
           "fill_m3": 0.0, "fill_interval_m3": [0.0, 0.0], "cut_area_m2": 0.0, "fill_area_m2": 0.0,
           "level_of_detection_m": 0.007, "warnings": []}
    text = format_change(rec) + "\n" + "\n".join(format_pile_changes(
        [{"old_pile": "P1", "new_pile": "P1", "change_interval_m3": [-0.03, 0.01], "centroid_m": [1.0, 2.0],
          "status": "matched", "change_m3": -0.01}]))
    assert "-0.0" not in text and "net change            +0.0 m³ (90 % interval 0.0 to 0.0 m³)" in text


def test_that_the_log_cell_says_whether_the_payload_closed_the_log_and_nothing_of_a_value_it_cannot_read():
    base = {"blocks_ok": 9, "blocks_corrupt": 0, "blocks_truncated": 0}
    assert render._fmt_log({**base, "closed_cleanly": True}).endswith("; closed by its writer")
    assert "not closed: cut short" in render._fmt_log({**base, "closed_cleanly": False})
    for unknown in (None, 1, [True], "yes"):  # an older writer's log, or a report.json edited by hand
        assert render._fmt_log({**base, "closed_cleanly": unknown}) == "9 ok, 0 corrupt, 0 truncated"
