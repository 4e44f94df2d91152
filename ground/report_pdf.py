"""report.pdf: the page of report.html as A4 pages, composed with matplotlib (no browser needed).

Built from the same `ReportContent` as report.md and report.html, in the same order, so the three cannot
disagree on a number: the title block, the volume and verdict, the piles, the warnings, the map, 3D view and
sections, then the engineer's details. The figures are the PNGs the report already wrote, placed
unresampled (no second rendering). Text is real text, searchable and read back in tests with pypdf
(`pdf_fonts`: the standard Helvetica when it can hold every character, else embedded TrueType).

Why not headless Chromium's --print-to-pdf: the report command must run where no browser is installed
(a site laptop, the Raspberry Pi's image), and a deliverable that looks different depending on which
machine made it is worse than one plain layout everywhere. docs/design-notes.md has the reasoning.
"""

from __future__ import annotations

import logging
import textwrap
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import matplotlib
import matplotlib.image as mpimg
import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.backends.backend_pdf import PdfPages
from matplotlib.figure import Figure

from ground.render import (
    ENGINEER_NOTE,
    REPORT_TITLE,
    ImageMap,
    ReportContent,
    build_content,
    config_note,
    warning_parts,
)

A4_IN = (8.27, 11.69)
BULLET_HANG_IN = 0.18
"""How far a list item's text sits right of its mark (and a nested list right of its parent's text), inches."""
MARGIN_IN = 0.6
BODY_PT = 8.5
SMALL_PT = 7.0
LINE_FACTOR = 1.35
"""Line height as a multiple of the font size."""
ASCENT_EM = 0.8
"""Where a line's baseline sits below its top, in its font size (Helvetica's and DejaVu Sans' ascenders reach 0.72-0.76
em): every line on one grid, whatever glyphs it holds."""
CHAR_WIDTH_EM = 0.55
"""DejaVu Sans' mean character width (em): how many characters a line of a given width holds."""
PT_PER_IN = 72.0
BOLD_WIDTH = 1.1
"""Bold characters are about this much wider than regular ones."""
CELL_PAD_IN = 0.12
"""Room left between a table's columns."""


class _Pages:
    """A top-to-bottom flow of text lines, tables and images over A4 pages (figure coordinates in inches)."""

    def __init__(self) -> None:
        self.pages: list[Figure] = []
        self.y_in = 0.0
        self.new_page()

    @property
    def fig(self) -> Figure:
        return self.pages[-1]

    @property
    def width_in(self) -> float:
        return A4_IN[0] - 2 * MARGIN_IN

    def new_page(self) -> None:
        fig = Figure(figsize=A4_IN)
        FigureCanvasAgg(fig)
        self.pages.append(fig)
        self.y_in = MARGIN_IN

    def _room(self, height_in: float) -> None:
        if self.y_in + height_in > A4_IN[1] - MARGIN_IN and self.y_in > MARGIN_IN:
            self.new_page()

    def _put(self, x_in: float, text: str, size: float, dy_in: float = 0.0, **kw) -> None:
        """One line of text at x_in, dy_in below the current line's top."""
        # On a baseline ASCENT_EM below the line's top, not aligned by its top: the top of a line is its tallest
        # glyph's, and with the standard fonts' metrics an apostrophe reaches 4 pt higher than a letter, which dropped
        # a line that held one half a line below its neighbours.
        baseline_in = self.y_in + dy_in + ASCENT_EM * size / PT_PER_IN
        self.fig.text(x_in / A4_IN[0], 1.0 - baseline_in / A4_IN[1], text, fontsize=size, va="baseline", ha="left",
                      **kw)

    def space(self, height_in: float) -> None:
        self.y_in += height_in

    def lines(self, text: str, size: float = BODY_PT, x_in: float = 0.0, width_in: float | None = None,
              **kw) -> None:
        """Wrapped text, one matplotlib text per line so a paragraph can break across pages."""
        width = (self.width_in - x_in) if width_in is None else width_in
        for line in wrap(text, width, size) or [""]:
            self._room(size * LINE_FACTOR / PT_PER_IN)
            self._put(MARGIN_IN + x_in, line, size, **kw)
            self.y_in += size * LINE_FACTOR / PT_PER_IN

    def bullet(self, mark: str, text: str, size: float = BODY_PT, x_in: float = 0.0) -> None:
        """A list item: `mark` at x_in, the text beside it, its wrapped lines under the text, not under the mark."""
        hang = BULLET_HANG_IN
        for i, line in enumerate(wrap(text, self.width_in - x_in - hang, size) or [""]):
            self._room(size * LINE_FACTOR / PT_PER_IN)
            if i == 0:
                self._put(MARGIN_IN + x_in, mark, size)
            self._put(MARGIN_IN + x_in + hang, line, size)
            self.y_in += size * LINE_FACTOR / PT_PER_IN

    def heading(self, text: str, size: float = 12.0, keep_in: float = 0.0) -> None:
        """keep_in: the height of what must follow the heading on its page (a figure's)."""
        self._room(4 * size / PT_PER_IN + keep_in)  # never a heading alone at the foot of a page
        self.space(0.5 * size / PT_PER_IN)
        self.lines(text, size, fontweight="bold")
        self.space(0.2 * size / PT_PER_IN)

    def table(self, header: Sequence[str] | None, rows: Sequence[Sequence[str]], widths_in: Sequence[float],
              size: float = BODY_PT) -> None:
        """Rows of wrapped cells in columns of the given widths; the header (bold) repeats on a new page."""
        def row(cells: Sequence[str], bold: bool) -> None:
            fit = size * (BOLD_WIDTH if bold else 1.0)
            wrapped = [wrap(c, w - CELL_PAD_IN, fit) or [""] for c, w in zip(cells, widths_in, strict=True)]
            h = max(len(w) for w in wrapped) * size * LINE_FACTOR / PT_PER_IN
            if self.y_in + h > A4_IN[1] - MARGIN_IN:
                self.new_page()
                if header is not None and not bold:
                    row(header, True)
            x = MARGIN_IN
            for lines, w in zip(wrapped, widths_in, strict=True):
                for i, line in enumerate(lines):  # a line at a time, on the page's line grid
                    self._put(x, line, size, i * size * LINE_FACTOR / PT_PER_IN,
                              fontweight="bold" if bold else "normal")
                x += w
            self.y_in += h + 0.03
        if header is not None:
            self._room(3 * size * LINE_FACTOR / PT_PER_IN)  # the header with at least its first row
            row(header, True)
        for r in rows:
            row(r, False)

    def _image_size_in(self, img: np.ndarray, max_height_in: float) -> tuple[float, float]:
        h_px, w_px = img.shape[:2]
        w_in = self.width_in
        h_in = w_in * h_px / w_px
        if h_in > max_height_in:
            h_in, w_in = max_height_in, max_height_in * w_px / h_px
        return w_in, h_in

    def image_height_in(self, path: Path, caption: str, max_height_in: float) -> float:
        """The height `image` takes for this PNG and caption (0 when it cannot be read)."""
        try:
            img = mpimg.imread(path)
        except (OSError, ValueError, SyntaxError):
            return 0.0
        cap_in = len(wrap(caption, self.width_in, SMALL_PT)) * SMALL_PT * LINE_FACTOR / PT_PER_IN
        return self._image_size_in(img, max_height_in)[1] + cap_in + 0.1

    def image(self, path: Path, caption: str, max_height_in: float) -> None:
        """The PNG at the page's width (or max_height_in tall), unresampled, with its caption under it."""
        try:
            img = mpimg.imread(path)
        except (OSError, ValueError, SyntaxError):
            self.lines(f"Image not found: {caption} ({path.name})", SMALL_PT, color="#a00000")
            return
        w_in, h_in = self._image_size_in(img, max_height_in)
        cap_in = len(wrap(caption, self.width_in, SMALL_PT)) * SMALL_PT * LINE_FACTOR / PT_PER_IN
        self._room(h_in + cap_in + 0.1)
        x0 = MARGIN_IN + (self.width_in - w_in) / 2
        ax = self.fig.add_axes((x0 / A4_IN[0], 1.0 - (self.y_in + h_in) / A4_IN[1], w_in / A4_IN[0], h_in / A4_IN[1]))
        ax.imshow(img, interpolation="none")
        ax.set_axis_off()
        self.y_in += h_in + 0.05
        self.lines(caption, SMALL_PT, color="#555555")
        self.space(0.1)

    def number_pages(self) -> None:
        n = len(self.pages)
        for i, fig in enumerate(self.pages, start=1):
            fig.text(0.5, MARGIN_IN / 2 / A4_IN[1], f"{REPORT_TITLE} · page {i} of {n}", ha="center",
                     fontsize=SMALL_PT, color="#555555")


def wrap(text: str, width_in: float, size_pt: float) -> list[str]:
    """`text` broken into lines that fit `width_in` at `size_pt` (by DejaVu Sans' mean character width)."""
    chars = max(8, int(width_in * PT_PER_IN / (size_pt * CHAR_WIDTH_EM)))
    out: list[str] = []
    for para in str(text).splitlines() or [""]:
        out += textwrap.wrap(para, chars, break_long_words=True, break_on_hyphens=False) or [""]
    return out


def _pile_widths(n_cols: int, width_in: float) -> list[float]:
    """The pile table's columns: the name and material wider, the numbers equal."""
    if n_cols <= 2:
        return [width_in / max(n_cols, 1)] * n_cols
    rest = (width_in - 1.6) / (n_cols - 2)
    return [0.8, 0.8, *([rest] * (n_cols - 2))]


def compose(content: ReportContent) -> list[Figure]:
    """The report's A4 pages, in the page's order (see `ground.render.render_html`)."""
    p = _Pages()
    p.lines(REPORT_TITLE, 18.0, fontweight="bold")
    p.space(0.1)
    if content.metadata:
        p.table(None, content.metadata, [1.6, p.width_in - 1.6])
    p.space(0.1)
    p.lines(content.headline, 12.0, fontweight="bold")
    if content.verdict:
        p.lines(f"Verdict: {content.verdict}", 10.0)
    if content.to_narrow:
        p.lines(f"To narrow the interval: {'; '.join(content.to_narrow)}", SMALL_PT)
    head, rows = content.piles
    if rows:
        p.heading("Piles")
        p.lines(f"Found as {content.piles_method or 'connected regions'}.", SMALL_PT)
        p.space(0.05)
        p.table(head, rows, _pile_widths(len(head), p.width_in), SMALL_PT)
        if content.piles_note:
            p.lines(content.piles_note, SMALL_PT)
    if content.warnings:  # before the figures: the verdict asks the reader to read them first
        p.heading(f"Warnings ({len(content.warnings)})")
        for w in content.warnings:
            head, more = warning_parts(w)
            p.bullet("•", head)
            for m in more:
                p.bullet("–", m, x_in=BULLET_HANG_IN)
    else:  # a line, not a heading that a full page pushes onto a page of its own
        p.lines("Warnings: none.", BODY_PT)
    if content.page_images:
        first = content.page_images[0]
        p.heading("Map, 3D view and cross-sections", keep_in=p.image_height_in(first[1], first[0], 4.6))
        for caption, path in content.page_images:
            p.image(path, caption, 4.6)
    p.new_page()
    p.heading("Engineer's details", 14.0)
    p.lines(ENGINEER_NOTE)
    p.heading("Summary", 11.0)
    p.table(("Quantity", "Value"), content.summary, [2.6, p.width_in - 2.6])
    if content.images:
        first = content.images[0]
        p.heading("Figures", 11.0, keep_in=p.image_height_in(first[1], first[0], 4.6))
        for caption, path in content.images:
            p.image(path, caption, 4.6)
    if content.config:
        p.heading("Configuration (as flown)", 11.0)
        p.lines(config_note(content), SMALL_PT)
        p.table(("Key", "Value"), content.config, [2.6, p.width_in - 2.6], SMALL_PT)
    p.heading("Method", 11.0)
    p.lines(content.method)
    if content.extra:
        p.heading("All figures", 11.0)
        p.table(("Name", "Value"), content.extra, [2.6, p.width_in - 2.6], SMALL_PT)
    p.number_pages()
    return p.pages


def pdf_fonts(pages: Sequence[Figure]) -> dict[str, Any]:
    """The PDF's fonts: the standard Helvetica when every character is in its encoding (cp1252: nothing to
    embed, half the PDF's cost), else DejaVu Sans embedded as TrueType (any script, searchable)."""
    try:
        for fig in pages:
            for t in fig.texts:
                t.get_text().encode("cp1252")
    except UnicodeEncodeError:
        return {"pdf.fonttype": 42, "pdf.use14corefonts": False}
    return {"pdf.use14corefonts": True, "font.family": "sans-serif", "font.sans-serif": ["Helvetica"]}


def write_pdf(report: Mapping[str, Any], images: ImageMap | None, out_path: str | Path) -> Path:
    """Write report.pdf (A4, searchable text) with the content of report.html, and return its path."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    content = build_content(report, images)
    pages = compose(content)
    fm_log = logging.getLogger("matplotlib.font_manager")
    level = fm_log.level
    fm_log.setLevel(logging.ERROR)  # "Failed to find font weight normal for Helvetica, now using medium": the same
    try:
        with matplotlib.rc_context(pdf_fonts(pages)), PdfPages(out, metadata={"Title": REPORT_TITLE}) as pdf:
            for fig in pages:
                pdf.savefig(fig)
    finally:
        fm_log.setLevel(level)
    return out
