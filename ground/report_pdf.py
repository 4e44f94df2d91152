"""report.pdf: the page of report.html as A4 pages, typeset with fpdf2 (no browser needed).

Built from the same `ReportContent` as report.md and report.html, in the same order, so the three cannot
disagree on a number: the title block, the volume and verdict, the piles, the warnings, the map, 3D view and
sections, then the engineer's details. The figures are the PNGs the report already wrote, placed
unresampled (no second rendering). Text is real text, searchable and read back in tests with pypdf
(`pdf_font`: the standard Helvetica when it can hold every character, else DejaVu Sans embedded).

`compose` lays the pages out (pure: a list of `Page`s of placed lines and images, in inches from the page's top
left corner); `write_pdf` draws them. Why not headless Chromium's --print-to-pdf: the report command must run where
no browser is installed (a site laptop, the Raspberry Pi's image), and a deliverable that looks different depending
on which machine made it is worse than one plain layout everywhere. docs/design-notes.md has the reasoning.
"""

from __future__ import annotations

import enum
import textwrap
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ground.render import (
    ENGINEER_HEADING,
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
STANDARD_ENCODING = "cp1252"
"""What the PDF's standard fonts can show (WinAnsiEncoding): text beyond it needs an embedded font."""


class Align(enum.Enum):
    """Where a line's x is: its left end or its centre."""
    LEFT = "left"
    CENTER = "center"


@dataclass(frozen=True)
class Line:
    """One line of text on its baseline, baseline_in below the page's top edge."""
    x_in: float
    baseline_in: float
    text: str
    size_pt: float
    bold: bool = False
    color: str = "#000000"
    align: Align = Align.LEFT


@dataclass(frozen=True)
class Picture:
    """A PNG placed with its top left corner at (x_in, top_in), w_in by h_in."""
    path: Path
    x_in: float
    top_in: float
    w_in: float
    h_in: float


@dataclass
class Page:
    """One A4 page's lines and pictures, in the order they were laid out."""
    lines: list[Line] = field(default_factory=list)
    pictures: list[Picture] = field(default_factory=list)


class PdfFont(enum.Enum):
    """The font every line is set in: the standard Helvetica (nothing embedded) or DejaVu Sans, embedded."""
    STANDARD = "helvetica"
    EMBEDDED = "dejavu"


def png_size_px(path: Path) -> tuple[int, int] | None:
    """An image's (width, height) in pixels, its chunks' checksums verified, or None when it cannot be read (gone,
    truncated, not an image): the page then says so instead of failing the whole PDF."""
    from PIL import Image, UnidentifiedImageError
    try:
        with Image.open(path) as im:
            size = im.size
            im.verify()
    except (OSError, ValueError, SyntaxError, UnidentifiedImageError):
        return None
    return size if size[0] > 0 and size[1] > 0 else None


class _Pages:
    """A top-to-bottom flow of text lines, tables and images over A4 pages (figure coordinates in inches)."""

    def __init__(self) -> None:
        self.pages: list[Page] = []
        self.y_in = 0.0
        self.new_page()

    @property
    def page(self) -> Page:
        return self.pages[-1]

    @property
    def width_in(self) -> float:
        return A4_IN[0] - 2 * MARGIN_IN

    def new_page(self) -> None:
        self.pages.append(Page())
        self.y_in = MARGIN_IN

    def _room(self, height_in: float) -> None:
        if self.y_in + height_in > A4_IN[1] - MARGIN_IN and self.y_in > MARGIN_IN:
            self.new_page()

    def _put(self, x_in: float, text: str, size: float, dy_in: float = 0.0, bold: bool = False,
             color: str = "#000000") -> None:
        """One line of text at x_in, dy_in below the current line's top."""
        # On a baseline ASCENT_EM below the line's top, not aligned by its top: the top of a line is its tallest
        # glyph's, and with the standard fonts' metrics an apostrophe reaches 4 pt higher than a letter, which dropped
        # a line that held one half a line below its neighbours.
        baseline_in = self.y_in + dy_in + ASCENT_EM * size / PT_PER_IN
        self.page.lines.append(Line(x_in, baseline_in, text, size, bold, color))

    def space(self, height_in: float) -> None:
        self.y_in += height_in

    def lines(self, text: str, size: float = BODY_PT, x_in: float = 0.0, width_in: float | None = None,
              bold: bool = False, color: str = "#000000") -> None:
        """Wrapped text, placed a line at a time so a paragraph can break across pages."""
        width = (self.width_in - x_in) if width_in is None else width_in
        for line in wrap(text, width, size) or [""]:
            self._room(size * LINE_FACTOR / PT_PER_IN)
            self._put(MARGIN_IN + x_in, line, size, bold=bold, color=color)
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
        self.lines(text, size, bold=True)
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
                    self._put(x, line, size, i * size * LINE_FACTOR / PT_PER_IN, bold=bold)
                x += w
            self.y_in += h + 0.03
        if header is not None:
            self._room(3 * size * LINE_FACTOR / PT_PER_IN)  # the header with at least its first row
            row(header, True)
        for r in rows:
            row(r, False)

    def _image_size_in(self, size_px: tuple[int, int], max_height_in: float) -> tuple[float, float]:
        w_px, h_px = size_px
        w_in = self.width_in
        h_in = w_in * h_px / w_px
        if h_in > max_height_in:
            h_in, w_in = max_height_in, max_height_in * w_px / h_px
        return w_in, h_in

    def image_height_in(self, path: Path, caption: str, max_height_in: float) -> float:
        """The height `image` takes for this PNG and caption (0 when it cannot be read)."""
        size = png_size_px(path)
        if size is None:
            return 0.0
        cap_in = len(wrap(caption, self.width_in, SMALL_PT)) * SMALL_PT * LINE_FACTOR / PT_PER_IN
        return self._image_size_in(size, max_height_in)[1] + cap_in + 0.1

    def image(self, path: Path, caption: str, max_height_in: float) -> None:
        """The PNG at the page's width (or max_height_in tall), unresampled, with its caption under it."""
        size = png_size_px(path)
        if size is None:
            self.lines(f"Image not found: {caption} ({Path(path).name})", SMALL_PT, color="#a00000")
            return
        w_in, h_in = self._image_size_in(size, max_height_in)
        cap_in = len(wrap(caption, self.width_in, SMALL_PT)) * SMALL_PT * LINE_FACTOR / PT_PER_IN
        self._room(h_in + cap_in + 0.1)
        self.page.pictures.append(Picture(Path(path), MARGIN_IN + (self.width_in - w_in) / 2, self.y_in, w_in, h_in))
        self.y_in += h_in + 0.05
        self.lines(caption, SMALL_PT, color="#555555")
        self.space(0.1)

    def number_pages(self) -> None:
        n = len(self.pages)
        for i, page in enumerate(self.pages, start=1):
            page.lines.append(Line(A4_IN[0] / 2, A4_IN[1] - MARGIN_IN / 2, f"{REPORT_TITLE} · page {i} of {n}",
                                   SMALL_PT, color="#555555", align=Align.CENTER))


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


def compose(content: ReportContent) -> list[Page]:
    """The report's A4 pages, in the page's order (see `ground.render.render_html`)."""
    p = _Pages()
    p.lines(REPORT_TITLE, 18.0, bold=True)
    p.space(0.1)
    if content.metadata:
        p.table(None, content.metadata, [1.6, p.width_in - 1.6])
    p.space(0.1)
    p.lines(content.headline, 12.0, bold=True)
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
    p.heading(ENGINEER_HEADING, 14.0)
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


def pdf_font(pages: Sequence[Page]) -> PdfFont:
    """The PDF's font: the standard Helvetica when every character is in its encoding (cp1252: nothing to embed, a
    tenth of the PDF's cost), else DejaVu Sans embedded (any script the font holds, searchable)."""
    try:
        for page in pages:
            for line in page.lines:
                line.text.encode(STANDARD_ENCODING)
    except UnicodeEncodeError:
        return PdfFont.EMBEDDED
    return PdfFont.STANDARD


def _dejavu(bold: bool) -> Path:
    """DejaVu Sans as matplotlib ships it (a dependency of the ground station already: no font to install)."""
    import matplotlib
    return Path(matplotlib.get_data_path()) / "fonts" / "ttf" / ("DejaVuSans-Bold.ttf" if bold else "DejaVuSans.ttf")


def _rgb(color: str) -> tuple[int, int, int]:
    return int(color[1:3], 16), int(color[3:5], 16), int(color[5:7], 16)


def draw(pages: Sequence[Page], out: Path) -> None:
    """Draw the laid-out pages into a PDF file with fpdf2 (inches, from the top left corner)."""
    from fpdf import FPDF
    from fpdf.errors import FPDFException
    pdf = FPDF(unit="in", format="A4")
    pdf.set_auto_page_break(False)
    pdf.set_margin(0)
    pdf.set_title(REPORT_TITLE)
    pdf.set_creator("pilescan")
    font = pdf_font(pages)
    if font is PdfFont.EMBEDDED:
        pdf.add_font(font.value, "", _dejavu(False))
        pdf.add_font(font.value, "B", _dejavu(True))
    else:
        pdf.core_fonts_encoding = STANDARD_ENCODING
    for page in pages:
        pdf.add_page()
        lines = list(page.lines)
        for pic in page.pictures:
            try:
                pdf.image(str(pic.path), x=pic.x_in, y=pic.top_in, w=pic.w_in, h=pic.h_in)
            except (OSError, ValueError, SyntaxError, FPDFException) as exc:  # read, yet not placeable: said, not fatal
                lines.append(Line(pic.x_in, pic.top_in + SMALL_PT / PT_PER_IN, f"Image could not be placed: "
                                  f"{pic.path.name} ({type(exc).__name__})", SMALL_PT, color="#a00000"))
        for line in lines:
            pdf.set_font(font.value, "B" if line.bold else "", line.size_pt)
            pdf.set_text_color(*_rgb(line.color))
            x = line.x_in if line.align is Align.LEFT else line.x_in - pdf.get_string_width(line.text) / 2
            pdf.text(x, line.baseline_in, line.text)
    pdf.output(str(out))


def write_pdf(report: Mapping[str, Any], images: ImageMap | None, out_path: str | Path) -> Path:
    """Write report.pdf (A4, searchable text) with the content of report.html, and return its path."""
    out = Path(out_path)
    out.parent.mkdir(parents=True, exist_ok=True)
    draw(compose(build_content(report, images)), out)
    return out
