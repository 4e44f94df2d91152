"""The report's page opened in a real browser (headless Chromium): its text, numbers and every image are there.

Two Chromium launches in all: the report itself (DOM and screenshot at once), and a copy with one image
broken, which shows that the page's image check can fail. Skipped only where no Chromium is installed;
.ci/run installs Debian's chromium, so CI runs it.
"""

from __future__ import annotations

import html
import json
import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from tools.report_screenshot import WINDOW_PX, find_chromium, golden_report, render

pytestmark = pytest.mark.skipif(find_chromium() is None,
                                reason="no Chromium installed (apt-get install chromium; .ci/run installs it)")


@pytest.fixture(scope="module")
def report_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("browser") / "report"
    golden_report(out)
    return out


def _text(dom: str) -> str:
    """The page's visible text, tags stripped and entities decoded, whitespace collapsed."""
    body = re.sub(r"<(script|style)\b.*?</\1>", " ", dom, flags=re.S)
    return " ".join(html.unescape(re.sub(r"<[^>]+>", " ", body)).split())


def test_that_chromium_shows_the_volume_its_interval_the_piles_and_every_image(report_dir, tmp_path):
    rep = json.loads((report_dir / "report.json").read_text())
    shot = tmp_path / "page.png"
    page = render(report_dir / "report.html", shot)
    loaded, total = page.images()
    n_img = len(re.findall(r"<img\b", page.dom))
    assert total == n_img == 6 and loaded == total  # map, 3D view, sections and the engineer's three
    text = _text(page.dom)
    lo, hi = rep["volume_interval_m3"]
    assert f"Stockpile volume: {rep['volume_m3']:,.1f} m³ (90 % interval {lo:,.1f} – {hi:,.1f} m³)" in text
    assert f"Verdict: {rep['verdict']}" in text
    assert rep["to_narrow_interval"] and f"To narrow the interval: {'; '.join(rep['to_narrow_interval'])}" in text
    assert rep["metadata"]["log_sha256"] in text
    piles = re.search(r'<table class="piles" id="piles">(.*?)</table>', page.dom, flags=re.S)
    assert piles is not None
    for p in rep["piles"]["piles"]:
        assert f"<td class=\"num\">{p['label']}</td>" in piles.group(1)
        assert f"{p['volume_m3']:,.1f}" in _text(piles.group(1))
    # The customer's part comes before the warnings and the engineer's details.
    assert text.index("Piles") < text.index("Warnings") < text.index("Map, 3D view and cross-sections") \
        < text.index("Engineer's details")
    img = mpimg.imread(shot)
    assert img.shape[:2] == (WINDOW_PX[1], WINDOW_PX[0])
    assert float(np.std(img[..., :3])) > 0.05  # drawn, not a blank page


def test_that_the_pages_image_check_counts_a_broken_image(report_dir, tmp_path):
    page = (report_dir / "report.html").read_text(encoding="utf-8")
    broken = re.sub(r'src="data:image/png;base64,[^"]*"', 'src="data:image/png;base64,AAAA"', page, count=1)
    assert broken != page
    (tmp_path / "broken.html").write_text(broken, encoding="utf-8")
    loaded, total = render(tmp_path / "broken.html").images()
    assert (loaded, total) == (5, 6)


def test_that_on_a_phone_the_page_is_no_wider_than_the_screen(report_dir, tmp_path):
    # the 10-column pile table and the figures table made a 390 px screen scroll an 854-908 px page sideways
    page = render(report_dir / "report.html", window_px=(390, 3000))
    width = re.search(r'<html[^>]*\bdata-page-width="(\d+)"', page.dom)
    view = re.search(r'<html[^>]*\bdata-view-width="(\d+)"', page.dom)
    assert width and view, "the page's script did not record its width"
    assert int(width.group(1)) <= int(view.group(1))
    assert '<div class="wide"><table class="piles" id="piles">' in page.dom  # the table scrolls in its own box
