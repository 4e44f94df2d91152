"""Open a report.html in headless Chromium: its DOM after load (with the page's image check) and a screenshot.

Usage: python -m tools.report_screenshot [REPORT_HTML] [--out docs/figures/report_page.png]
Without REPORT_HTML it reports the golden log (tests/golden) into a temporary folder first. Needs a Chromium
(Debian's `chromium`; .ci/run installs it); the report command itself never does.

One browser launch does both: --dump-dom after a virtual-time budget (the page's inline script has then set
data-images-loaded / data-images-total on <html>) and --screenshot. The browser is isolated from the network
and from any profile: a fresh --user-data-dir, no background networking, no component updates, no sync, and
the page is a local file that fetches nothing.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

CHROMIUM_NAMES = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
CHROMIUM_ENV = "PILESCAN_CHROMIUM"
"""An explicit browser binary, for machines where it is not on PATH under one of CHROMIUM_NAMES."""
DEFAULT_TIMEOUT_S = 60.0
"""A subprocess bound, not a measurement: a launch takes about a second on an idle machine."""
VIRTUAL_TIME_BUDGET_MS = 10_000
"""Virtual time the page gets before the DOM is dumped: decoding a few MB of inline PNGs fits many times over."""
WINDOW_PX = (1100, 2400)
"""The screenshot: a laptop's width, tall enough for the title block, verdict, piles, map and 3D view."""
FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
         "--disable-background-networking", "--disable-component-update", "--disable-sync",
         "--disable-dev-shm-usage", "--hide-scrollbars")
ROOT = Path(__file__).resolve().parents[1]
DEFAULT_OUT = ROOT / "docs" / "figures" / "report_page.png"


class BrowserError(RuntimeError):
    """Chromium failed, timed out or wrote nothing."""


def find_chromium() -> str | None:
    """The browser to use: $PILESCAN_CHROMIUM, else the first of CHROMIUM_NAMES on PATH; None if none."""
    explicit = os.environ.get(CHROMIUM_ENV)
    if explicit:
        return explicit if Path(explicit).is_file() else None
    for name in CHROMIUM_NAMES:
        found = shutil.which(name)
        if found:
            return found
    return None


@dataclass(frozen=True)
class Rendered:
    dom: str
    screenshot: Path | None

    def images(self) -> tuple[int, int]:
        """(loaded, total) as the page's image check recorded them; BrowserError when it never ran."""
        m_tot = re.search(r'<html[^>]*\bdata-images-total="(\d+)"', self.dom)
        m_ok = re.search(r'<html[^>]*\bdata-images-loaded="(\d+)"', self.dom)
        if not (m_tot and m_ok):
            raise BrowserError("the page's image check did not run (no data-images-* on <html>): no load event?")
        return int(m_ok.group(1)), int(m_tot.group(1))


def render(html_path: Path, screenshot: Path | None = None, *, browser: str | None = None,
           window_px: tuple[int, int] = WINDOW_PX, timeout_s: float = DEFAULT_TIMEOUT_S) -> Rendered:
    """Load html_path in headless Chromium once: the DOM after load and, if asked, a screenshot."""
    exe = browser or find_chromium()
    if exe is None:
        raise BrowserError(f"no Chromium found (install Debian's chromium, or set {CHROMIUM_ENV})")
    url = Path(html_path).resolve().as_uri()
    with tempfile.TemporaryDirectory(prefix="pilescan-chromium-") as profile:
        cmd = [exe, *FLAGS, f"--user-data-dir={profile}", f"--virtual-time-budget={VIRTUAL_TIME_BUDGET_MS}",
               f"--window-size={window_px[0]},{window_px[1]}", "--dump-dom"]
        if screenshot is not None:
            screenshot.parent.mkdir(parents=True, exist_ok=True)
            cmd.append(f"--screenshot={Path(screenshot).resolve()}")
        try:
            done = subprocess.run([*cmd, url], capture_output=True, text=True, timeout=timeout_s, check=False)
        except subprocess.TimeoutExpired:
            raise BrowserError(f"Chromium did not finish within {timeout_s:g} s") from None
    if done.returncode != 0 or "<html" not in done.stdout:
        tail = " | ".join(done.stderr.strip().splitlines()[-3:])
        raise BrowserError(f"Chromium exited with {done.returncode} and no DOM: {tail}")
    if screenshot is not None and not Path(screenshot).is_file():
        raise BrowserError(f"Chromium wrote no screenshot to {screenshot}")
    return Rendered(done.stdout, screenshot)


def golden_report(out_dir: Path) -> Path:
    """report.html of the golden log (tests/golden), written into out_dir."""
    from ground.report import make_report
    make_report(ROOT / "tests" / "golden", out_dir, force=True)
    return out_dir / "report.html"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("html", nargs="?", type=Path, help="a report.html (default: report the golden log)")
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"screenshot PNG (default {DEFAULT_OUT})")
    ap.add_argument("--timeout", type=float, default=DEFAULT_TIMEOUT_S, help="seconds Chromium may take")
    args = ap.parse_args(argv)
    try:
        with tempfile.TemporaryDirectory() as tmp:
            html = args.html if args.html is not None else golden_report(Path(tmp) / "report")
            if not html.is_file():
                print(f"report_screenshot: error: no such file: {html}", file=sys.stderr)
                return 2
            shot = render(html, args.out, timeout_s=args.timeout)
            loaded, total = shot.images()
    except BrowserError as exc:
        print(f"report_screenshot: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.out}: {loaded} of {total} images loaded")
    return 0 if loaded == total else 1


if __name__ == "__main__":
    raise SystemExit(main())
