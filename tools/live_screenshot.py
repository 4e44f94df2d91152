"""Fly a networked SITL survey that streams to `pilescan-ground listen --web`, watch the live page in headless
Chromium while it flies, and save a screenshot of it (docs/figures/live_page.png).

    python -m tools.live_screenshot [--out docs/figures/live_page.png] [--flight-s S] [--run-dir DIR]

Four processes on real sockets, as in the field: `pilescan-sitl serve --devices` (the autopilot and the
emulated LIDAR-Lite and servo), `pilescan-payload --stream udp:...` (the unchanged payload), `pilescan-ground
listen --stream ... --web 127.0.0.1:0 --header H` (H: the header of a SITL flight with the same building and
sensor, as an operator would give the header of an earlier flight) and the scripted ground station; plus
the browser. Without --flight-s the whole mission is flown (about a minute and a half of wall time).

The browser is driven over Chrome's DevTools protocol on a pipe (`--remote-debugging-pipe`: no port, no
websocket library), isolated as tools.report_screenshot's: a fresh profile, no background networking; the
page itself fetches nothing but its own server's /state.json. `LivePage.read()` returns what the page's
DOM shows, so the test (tests/tools/test_live_screenshot.py) checks the page a person would see.
"""

from __future__ import annotations

import argparse
import base64
import contextlib
import fcntl
import json
import os
import re
import select
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from tools.report_screenshot import FLAGS, ROOT, BrowserError, find_chromium

DEFAULT_OUT = ROOT / "docs" / "figures" / "live_page.png"
WINDOW_PX = (1280, 800)
"""The screenshot: a laptop's screen."""
STORAGE = "24x16x10"
MISSION_ARGS = ("--p-traj", "25", "--altitude", "9", "--speed", "2")
"""A small building flown fast: the whole mission in about a minute and a half of wall time."""
_PAGE_LINE = re.compile(r"live page on (http://\S+/)")

READ_PAGE_JS = """(() => {
  const d = (id) => document.getElementById(id), cv = d("map"), iv = d("interval");
  return {polls: Number(document.documentElement.dataset.polls || 0), status: d("status").textContent,
          records: Number(d("records").dataset.value || 0), records_text: d("records").textContent,
          volume_text: d("volume").textContent, volume: d("volume").dataset.value === undefined ? null
            : Number(d("volume").dataset.value),
          interval_text: iv.textContent, interval: iv.dataset.lo === undefined ? null
            : [Number(iv.dataset.lo), Number(iv.dataset.hi)],
          ra_text: d("ra").textContent, volume_records: Number(d("volume-age").dataset.records || 0),
          draws: Number(cv.dataset.draws || 0),
          cells_points: Number(cv.dataset.cellsPoints || 0), cells_between: Number(cv.dataset.cellsBetween || 0),
          cells_unseen: Number(cv.dataset.cellsUnseen || 0),
          track_points: Number(cv.dataset.trackPoints || 0),
          canvas: (() => { const r = cv.getBoundingClientRect();
                           return [r.left, r.top, r.width, r.height].map(Math.round); })()};
})()"""
"""What the page shows, read from its DOM (the ids and data-* attributes its script fills)."""


def _renumbered(fd: int, lowest: int = 10) -> int:
    """fd moved to a descriptor >= lowest (the old one closed)."""
    high = fcntl.fcntl(fd, fcntl.F_DUPFD, lowest)
    os.close(fd)
    return high


class Chromium:
    """Headless Chromium driven over the DevTools protocol on a pipe (fd 3 in, fd 4 out, NUL-terminated JSON).

    `open(url)` makes a page and attaches to it; `evaluate(js)`; `screenshot(path)`; `close()`.
    """

    def __init__(self, browser: str | None = None, window_px: tuple[int, int] = WINDOW_PX) -> None:
        exe = browser or find_chromium()
        if exe is None:
            raise BrowserError("no Chromium found (install Debian's chromium, or set PILESCAN_CHROMIUM)")
        self.window_px = window_px
        self._profile = tempfile.TemporaryDirectory(prefix="pilescan-chromium-")
        to_child_r, self._to_child = os.pipe()
        self._from_child, from_child_w = os.pipe()
        # The child's ends renumbered 10 and up, so that putting them at 3 and 4 cannot overwrite one another.
        to_child_r, from_child_w = _renumbered(to_child_r), _renumbered(from_child_w)
        args = [*FLAGS, f"--user-data-dir={self._profile.name}", f"--window-size={window_px[0]},{window_px[1]}",
                "--remote-debugging-pipe", "about:blank"]
        # The protocol wants fds 3 and 4 exactly: a small Python launcher puts the pipes there and execs the
        # browser (a POSIX shell's redirections take single-digit descriptors only).
        launch = ("import os, sys; a, b = int(sys.argv[1]), int(sys.argv[2]); os.dup2(a, 3); os.dup2(b, 4); "
                  "os.close(a); os.close(b); os.execv(sys.argv[3], sys.argv[3:])")
        self._proc = subprocess.Popen([sys.executable, "-c", launch, str(to_child_r), str(from_child_w), exe, *args],
                                      pass_fds=(to_child_r, from_child_w), stdin=subprocess.DEVNULL,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        os.close(to_child_r)
        os.close(from_child_w)
        self._buf = b""
        self._next_id = 0
        self._session: str | None = None

    def _send(self, method: str, params: dict | None = None, session: str | None = None,
              timeout_s: float = 30.0) -> dict:
        self._next_id += 1
        msg = {"id": self._next_id, "method": method, "params": params or {}}
        if session is not None:
            msg["sessionId"] = session
        try:
            os.write(self._to_child, json.dumps(msg).encode() + b"\0")
        except BrokenPipeError:
            raise BrowserError(f"Chromium has exited ({self._proc.poll()}) before {method}") from None
        deadline = time.monotonic() + timeout_s
        while True:
            while b"\0" in self._buf:
                raw, self._buf = self._buf.split(b"\0", 1)
                reply = json.loads(raw)
                if reply.get("id") == self._next_id:
                    if "error" in reply:
                        raise BrowserError(f"{method}: {reply['error'].get('message')}")
                    return reply.get("result", {})
            left = deadline - time.monotonic()
            if left <= 0:
                raise BrowserError(f"Chromium did not answer {method} within {timeout_s:g} s")
            ready, _, _ = select.select([self._from_child], [], [], left)
            if ready:
                chunk = os.read(self._from_child, 1 << 20)
                if not chunk:
                    raise BrowserError(f"Chromium closed its pipe (exit {self._proc.poll()}) during {method}")
                self._buf += chunk

    def open(self, url: str) -> None:
        target = self._send("Target.createTarget", {"url": url})["targetId"]
        self._session = self._send("Target.attachToTarget", {"targetId": target, "flatten": True})["sessionId"]
        w, h = self.window_px
        self._send("Emulation.setDeviceMetricsOverride", {"width": w, "height": h, "deviceScaleFactor": 1,
                                                          "mobile": False}, self._session)

    def evaluate(self, expression: str):
        """The value of a JS expression in the page (JSON-able)."""
        res = self._send("Runtime.evaluate", {"expression": expression, "returnByValue": True}, self._session)
        if "exceptionDetails" in res:
            raise BrowserError(f"the page's script failed: {res['exceptionDetails'].get('text')}")
        return res.get("result", {}).get("value")

    def screenshot(self, path: Path) -> Path:
        data = self._send("Page.captureScreenshot", {"format": "png"}, self._session)["data"]
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(base64.b64decode(data))
        return path

    def close(self) -> None:
        with contextlib.suppress(BrowserError, OSError):
            self._send("Browser.close", timeout_s=5.0)
        try:
            self._proc.wait(timeout=10.0)
        except subprocess.TimeoutExpired:
            self._proc.kill()
            self._proc.wait()
        for fd in (self._to_child, self._from_child):
            with contextlib.suppress(OSError):
                os.close(fd)
        self._profile.cleanup()

    def __enter__(self) -> Chromium:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


@dataclass(frozen=True)
class PageView:
    """What the live page showed at one moment (READ_PAGE_JS)."""

    polls: int
    status: str
    records: int
    records_text: str
    volume_text: str
    volume: float | None
    interval_text: str
    interval: list[float] | None
    ra_text: str
    volume_records: int
    draws: int
    cells_points: int
    cells_between: int
    cells_unseen: int
    track_points: int
    canvas: list[int]


class LivePage:
    """The live page open in a Chromium."""

    def __init__(self, browser: Chromium, url: str, timeout_s: float = 30.0) -> None:
        self.browser = browser
        browser.open(url)
        deadline = time.monotonic() + timeout_s  # the navigation is asynchronous: wait for the page's load
        while browser.evaluate("document.readyState + ' ' + location.href") != f"complete {url}":
            if time.monotonic() > deadline:
                raise BrowserError(f"the page {url} did not load within {timeout_s:g} s")
            time.sleep(0.2)

    def read(self) -> PageView:
        return PageView(**self.browser.evaluate(READ_PAGE_JS))

    def wait_for(self, condition: Callable[[PageView], bool], timeout_s: float, what: str) -> PageView:
        """Read the page until condition holds; BrowserError naming `what` (and the last view) at the deadline."""
        deadline = time.monotonic() + timeout_s
        while True:
            view = self.read()
            if condition(view):
                return view
            if time.monotonic() > deadline:
                raise BrowserError(f"the page did not show {what} within {timeout_s:g} s; last: {view}")
            time.sleep(0.5)


def sitl_header(storage: str = STORAGE) -> dict:
    """The header of a SITL flight over this building with the payload's defaults (lever arm, LIDAR-Lite)."""
    from firmware_py.core.storage import Storage
    from sitl.missions.rectangle import Mission
    from sitl.runners.fly import FlyConfig, log_header
    cfg = FlyConfig(mission=Mission(storage=Storage.parse(storage), p_traj=0.25, altitude_m=9.0, speed_m_s=2.0))
    return log_header(cfg, cfg.servo_waveform())


class Listen:
    """`python -m ground.cli listen --web` as its own process; `url` once it has said where its page is."""

    def __init__(self, stream_port: int, header: Path, out: Path, timeout_s: float = 60.0) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "ground.cli", "listen", "--stream", f"udp:127.0.0.1:{stream_port}",
             "--web", "127.0.0.1:0", "--header", str(header), "--out", str(out), "--force"],
            cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        self.lines: list[str] = []
        self._stopped: tuple[int, str] | None = None
        self._url: str | None = None
        self._seen = threading.Event()
        self._thread = threading.Thread(target=self._read, daemon=True)
        self._thread.start()
        if not self._seen.wait(timeout_s) or self._url is None:
            self.stop()
            raise RuntimeError(f"listen did not say where its page is: {' | '.join(self.lines[-5:])}")

    @property
    def url(self) -> str:
        return self._url

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.append(line.rstrip("\n"))
            m = _PAGE_LINE.search(line)
            if m and self._url is None:
                self._url = m.group(1)
                self._seen.set()
        self._seen.set()  # ended without the line

    def stop(self, timeout_s: float = 30.0) -> tuple[int, str]:
        """SIGTERM (listen's clean stop), its exit code and summary (stdout); again: the same."""
        if self._stopped is not None:
            return self._stopped
        if self.proc.poll() is None:
            self.proc.terminate()
        try:
            out, _ = self.proc.communicate(timeout=timeout_s)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            out, _ = self.proc.communicate()
        self._thread.join(timeout=2.0)
        self._stopped = (self.proc.returncode, out or "")
        return self._stopped


@contextlib.contextmanager
def live_flight(run_dir: Path, flight_s: float | None) -> Iterator[tuple[Listen, threading.Thread, dict]]:
    """listen --web up, then the networked flight streaming to it on a thread; yields (listen, flight thread,
    the flight's outcome: {"run": NetworkedRun} or {"error": exc} once the thread ends). listen is stopped on
    exit if the caller has not."""
    from tools.fly_networked import fly_networked, free_port
    run_dir.mkdir(parents=True, exist_ok=True)
    header = run_dir / "header.json"
    header.write_text(json.dumps(sitl_header()))
    port = free_port(__import__("socket").SOCK_DGRAM)
    listen = Listen(port, header, run_dir / "live.pslog")
    outcome: dict = {}

    def fly() -> None:
        try:
            outcome["run"] = fly_networked(list(MISSION_ARGS), STORAGE, "1", run_dir / "flight", flight_s=flight_s,
                                           say=lambda _m: None, report=False,
                                           payload_args=["--stream", f"udp:127.0.0.1:{port}"])
        except Exception as exc:  # reported by the caller, who joins the thread
            outcome["error"] = exc
    flight = threading.Thread(target=fly, name="networked-flight", daemon=True)
    flight.start()
    try:
        yield listen, flight, outcome
    finally:
        flight.join(timeout=300.0)
        listen.stop()


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", type=Path, default=DEFAULT_OUT, help=f"screenshot PNG (default {DEFAULT_OUT})")
    ap.add_argument("--flight-s", type=float, default=None, metavar="S",
                    help="stop the payload S seconds after AUTO (default: fly the whole mission)")
    ap.add_argument("--run-dir", type=Path, default=None, help="keep the flight's files here (default: a temporary "
                                                                 "folder)")
    args = ap.parse_args(argv)
    if args.flight_s is not None and not args.flight_s > 0:
        print(f"live_screenshot: error: --flight-s must be > 0, got {args.flight_s:g}", file=sys.stderr)
        return 2
    try:
        with tempfile.TemporaryDirectory() as tmp, Chromium() as browser:
            run_dir = args.run_dir or Path(tmp)
            shot, view = Path(tmp) / "live.png", None
            with live_flight(run_dir, args.flight_s) as (listen, flight, outcome):
                page = LivePage(browser, listen.url)
                while flight.is_alive():  # the last view with a volume while the stream still flows
                    now = page.read()
                    if now.volume is not None and now.interval is not None and now.status == "receiving":
                        browser.screenshot(shot)
                        view = now
                    flight.join(5.0)
                if "error" in outcome:
                    raise outcome["error"]
            if view is None:
                raise RuntimeError("the page never showed a volume while the stream flowed: fly longer")
            args.out.parent.mkdir(parents=True, exist_ok=True)
            args.out.write_bytes(shot.read_bytes())
    except (BrowserError, RuntimeError, OSError) as exc:
        print(f"live_screenshot: error: {exc}", file=sys.stderr)
        return 1
    print(f"{args.out}: {view.records_text} records, {view.volume_text} ({view.interval_text}), "
          f"R_a {view.ra_text}, map cells: {view.cells_points} with points, {view.cells_between} between, "
          f"{view.cells_unseen} unseen")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
