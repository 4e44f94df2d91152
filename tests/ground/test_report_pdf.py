"""report.pdf: the page's content on A4 pages, read back with pypdf (a reader nobody here wrote): its page
count, its numbers and names, tables that break across pages without losing a row, a missing image said."""

from __future__ import annotations

import itertools
import re

import matplotlib.image as mpimg
import numpy as np
import pytest
from pypdf import PdfReader

from ground import report_pdf
from ground.piles import PileOptions, pile_table
from ground.render import build_content
from ground.report import ReportOptions, make_report
from ground.surface import Grid

A4_PT = (595.3, 841.9)


def a_report() -> dict:
    g = Grid(20.0, 10.0, 0.25)
    xc = 0.5 * (g.x_edges[:-1] + g.x_edges[1:])
    x, y = np.meshgrid(xc, 0.5 * (g.y_edges[:-1] + g.y_edges[1:]), indexing="ij")
    h = np.clip(3 - np.hypot(x - 6, y - 5), 0, None) + np.clip(2 - np.hypot(x - 15, y - 5), 0, None)
    return {"volume_m3": 12345.678, "volume_interval_m3": [12000.0, 12700.5], "true_volume_m3": None,
            "verdict": "12,346 m³ (90 % interval 12,000–12,701 m³); limited by: the sensor's noise",
            "metadata": {"site_name": "North shed", "log_sha256": "ab" * 32, "operator": "J. Smith"},
            "piles": pile_table(h, g, 0.03, PileOptions(density_kg_m3=1600.0), None),
            "warnings": ["only 80.0 % of the floor is reconstructed"], "software_version": "pilescan 0.1.0"}


@pytest.fixture
def images(tmp_path):
    rng = np.random.default_rng(0)
    out = {}
    for name in ("site_map", "surface_3d", "sections", "cloud", "height_map", "coverage"):
        mpimg.imsave(tmp_path / f"{name}.png", rng.random((300, 440)))
        out[name] = tmp_path / f"{name}.png"
    return out


def read(path) -> tuple[PdfReader, list[str]]:
    r = PdfReader(path)
    return r, [p.extract_text() for p in r.pages]


def test_that_the_pdf_holds_the_volume_verdict_metadata_and_piles_on_numbered_a4_pages(tmp_path, images):
    rep = a_report()
    out = report_pdf.write_pdf(rep, images, tmp_path / "report.pdf")
    r, pages = read(out)
    n = len(r.pages)
    assert n == len(report_pdf.compose(build_content(rep, images)))
    assert n >= 3  # the title page, the figures, the engineer's details
    for i, page in enumerate(r.pages):
        assert (float(page.mediabox.width), float(page.mediabox.height)) == pytest.approx(A4_PT, abs=1)
        assert f"page {i + 1} of {n}" in pages[i]
    first = pages[0]
    assert "Stockpile volume: 12,345.7 m³ (90 % interval 12,000.0 – 12,700.5 m³)" in first
    assert "North shed" in first and "J. Smith" in first and "ab" * 32 in first
    assert "limited by: the sensor's noise" in first
    for p in rep["piles"]["piles"]:
        assert p["label"] in first and f"{p['volume_m3']:,.1f}" in first
    text = "\n".join(pages)
    # the warnings the verdict counts come before the figures they qualify
    assert text.index("Piles") < text.index("Warnings (1)") < text.index("Map, 3D view and cross-sections") \
        < text.index("Engineer's details")
    assert "only 80.0 % of the floor is reconstructed" in text
    assert "True volume" not in text and "Ve (eq. 8)" not in text  # no reference: no rows for it


def test_that_a_long_table_breaks_across_pages_without_losing_a_row(tmp_path):
    rep = {"volume_m3": 1.0, **{f"key_{i:03d}": i for i in range(400)}}
    r, pages = read(report_pdf.write_pdf(rep, None, tmp_path / "r.pdf"))
    text = "\n".join(pages)
    assert len(r.pages) >= 3
    assert all(f"key_{i:03d}" in text for i in range(400))


def test_that_a_missing_image_is_said_in_the_pdf(tmp_path):
    _, pages = read(report_pdf.write_pdf({"volume_m3": 1.0}, {"site_map": tmp_path / "gone.png"},
                                         tmp_path / "r.pdf"))
    assert "Image not found" in "\n".join(pages) and "gone.png" in "\n".join(pages)


def test_that_an_image_the_pdf_writer_cannot_place_is_said_and_the_rest_is_written(tmp_path, images, monkeypatch):
    import fpdf
    real = fpdf.FPDF.image

    def image(self, name, *a, **kw):
        if str(name).endswith("sections.png"):
            raise fpdf.errors.FPDFException("unsupported PNG")
        return real(self, name, *a, **kw)

    monkeypatch.setattr(fpdf.FPDF, "image", image)
    r, pages = read(report_pdf.write_pdf(a_report(), images, tmp_path / "r.pdf"))
    text = "\n".join(pages)
    assert "Image could not be placed: sections.png (FPDFException)" in text and "page 1 of" in pages[0]
    drawn = [re.findall(r"/(\w+)\s+Do\b", p.get_contents().get_data().decode("latin-1")) for p in r.pages]
    assert sum(len(d) for d in drawn) == len(images) - 1  # every other figure placed


def test_that_a_warning_of_many_clauses_is_a_bulleted_headline_with_its_clauses_hanging_under_it(tmp_path):
    warning = "pose corrected: 0.14 m (0.20 max; over time); " + "; ".join(f"clause {i} " + "word " * 30
                                                                         for i in range(3))
    pages = report_pdf.compose(build_content({"volume_m3": 1.0, "warnings": [warning]}, None))
    texts = [t for page in pages for t in page.lines]
    head = next(t for t in texts if t.text == "pose corrected: 0.14 m (0.20 max; over time)")
    marks = [t for t in texts if t.text == "–"]
    assert len(marks) == 3  # one mark per clause, however many lines each wraps to
    lines = [t for t in texts if t.text.startswith(("clause", "word"))]
    assert len(lines) > 3 and len({round(t.x_in, 6) for t in lines}) == 1  # wrapped lines hang level
    assert lines[0].x_in > marks[0].x_in > head.x_in - 1e-9


def test_that_every_line_sits_on_one_grid_whatever_glyphs_it_holds():
    p = report_pdf._Pages()
    p.lines("the floor's level")  # an apostrophe reaches higher than any letter in the standard fonts' metrics
    p.lines("a plain line")
    p.table(("Quantity", "Value"), [("Pose source", "position " * 24), ("next", "row")], [2.0, 2.0])
    texts = p.page.lines
    assert all("\n" not in t.text for t in texts)  # a line at a time, each on its baseline
    step = report_pdf.BODY_PT * report_pdf.LINE_FACTOR / report_pdf.PT_PER_IN
    y = [t.baseline_in for t in texts]  # inches down from the page's top
    assert y[1] - y[0] == pytest.approx(step)
    value_lines = [t for t in texts if t.text.startswith("position")]
    assert len(value_lines) > 1 and all(b.baseline_in - a.baseline_in == pytest.approx(step)
                                        for a, b in itertools.pairwise(value_lines))
    nxt = next(t for t in texts if t.text == "next")
    assert nxt.baseline_in > value_lines[-1].baseline_in + step * 0.99  # the next row below the cell


def test_that_wrapping_keeps_every_word_and_fits_the_width():
    text = "word " * 200 + "a" * 300
    lines = report_pdf.wrap(text, 3.0, 10.0)
    chars = int(3.0 * 72 / (10.0 * report_pdf.CHAR_WIDTH_EM))
    assert all(len(line) <= chars for line in lines)
    assert "".join(lines).replace(" ", "") == text.replace(" ", "")


def test_that_the_report_command_writes_a_pdf_of_the_report(tmp_path):
    rep = make_report("tests/golden", tmp_path / "rep", ReportOptions())
    r, pages = read(tmp_path / "rep" / "report.pdf")
    assert len(r.pages) >= 4  # the title page and its figures, the engineer's details and figures
    assert f"Stockpile volume: {rep['volume_m3']:,.1f} m³" in pages[0]
    assert rep["verdict"] in " ".join(pages[0].split())
    assert rep["to_narrow_interval"] and "; ".join(rep["to_narrow_interval"]) in " ".join(pages[0].split())
    drawn = [re.findall(r"/(\w+)\s+Do\b", p.get_contents().get_data().decode("latin-1")) for p in r.pages]
    assert sum(len(d) for d in drawn) == len({n for d in drawn for n in d}) == 6  # each figure once


def test_that_text_beyond_the_standard_fonts_is_embedded_and_still_reads_back(tmp_path):
    """Helvetica (nothing embedded) covers cp1252 only; a Cyrillic site name needs the embedded TrueType."""
    latin = {"volume_m3": 1.0, "metadata": {"site_name": "Zürich Süd – bay 3"}}
    cyrillic = {"volume_m3": 1.0, "metadata": {"site_name": "Склад 3"}}
    assert report_pdf.pdf_font(report_pdf.compose(build_content(latin, None))) is report_pdf.PdfFont.STANDARD
    assert report_pdf.pdf_font(report_pdf.compose(build_content(cyrillic, None))) is report_pdf.PdfFont.EMBEDDED
    for rep, embedded in ((latin, False), (cyrillic, True)):
        r, pages = read(report_pdf.write_pdf(rep, None, tmp_path / "r.pdf"))
        assert rep["metadata"]["site_name"] in pages[0]
        fonts = {f["/BaseFont"] for p in r.pages for f in p["/Resources"]["/Font"].values()}
        assert ("Helvetica" in str(fonts)) is not embedded and ("DejaVu" in str(fonts)) is embedded
