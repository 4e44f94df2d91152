"""`listen --web HOST:PORT`: the live page and its JSON, served while the stream is received.

Two paths and nothing else: ``/`` (the page: HTML with its CSS and script inline, so a browser with no
network beyond this server shows it whole) and ``/state.json`` (`ground.live_state.LiveState.snapshot`);
any other path is 404, any method but GET and HEAD 501. The page polls the JSON once a second and draws
the building, the coverage map (cells with points by their height, paler where the fitted surface
spans the gaps between them), the cells still unseen (no surface there yet: what R_a misses), the
vehicle's track and position; beside it the running volume with its 90 % interval and age, R_a, the receiver's
counters and the time since the last records ("no data for N s" once the stream stops).

The server is the standard library's `ThreadingHTTPServer` on a daemon thread: a browser that goes
away mid-response costs its own handler thread one caught error, never the receiver; a client that
sends nothing is dropped after `REQUEST_TIMEOUT_S`. It binds where it is told (the advice: 127.0.0.1,
since the page has no authentication: docs/live.md); a port in use or an address not of this machine
is a one-line `UserError`. A Content-Security-Policy lets the page reach nothing but its own server.
"""

from __future__ import annotations

import socket
import threading
from collections.abc import Callable
from http import HTTPStatus
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer
from typing import Any
from urllib.parse import urlsplit

from firmware_py.core.cli import UserError

REQUEST_TIMEOUT_S = 10.0
"""A connection that sends no complete request within this long is closed (a stalled client holds no thread)."""
CSP = ("default-src 'none'; script-src 'unsafe-inline'; style-src 'unsafe-inline'; connect-src 'self'; "
       "img-src 'self' data:; base-uri 'none'; form-action 'none'; frame-ancestors 'none'")
"""The page may run its inline script and style and fetch from its own server only: nothing from outside."""
PAGE_PATHS = ("/", "/index.html")
STATE_PATH = "/state.json"


def parse_web_address(text: str) -> tuple[str, int]:
    """`--web` value -> (host, port): HOST:PORT or [IPv6]:PORT, port 0-65535 (0: any free port, printed).
    ValueError (one line) for anything else."""
    form = "HOST:PORT or [IPv6]:PORT (e.g. 127.0.0.1:8080)"
    t = text.strip() if isinstance(text, str) else ""
    if t.startswith("["):
        end = t.find("]")
        host, rest = (t[1:end], t[end + 1:]) if end > 0 else ("", "")
        if not rest.startswith(":"):
            raise ValueError(f"--web must look like {form}, got {text!r}")
        port = rest[1:]
    elif t.count(":") == 1:
        host, port = t.split(":")
    else:
        raise ValueError(f"--web must look like {form}, got {text!r}")
    if not host or any(c.isspace() or c in "/?#@[]" for c in host):
        raise ValueError(f"--web must look like {form}, got {text!r}")
    if not (port.isascii() and port.isdigit() and int(port) <= 65535):
        raise ValueError(f"--web port must be 0-65535 in {text!r}")
    return host, int(port)


def web_url(host: str, port: int) -> str:
    """The page's address as a browser takes it."""
    return f"http://[{host}]:{port}/" if ":" in host else f"http://{host}:{port}/"


class _Server(ThreadingHTTPServer):
    daemon_threads = True
    allow_reuse_address = True  # a restarted listen gets its port back at once (TIME_WAIT), not "in use"

    def __init__(self, address: tuple[str, int], state_json: Callable[[], bytes]) -> None:
        self.address_family = socket.AF_INET6 if ":" in address[0] else socket.AF_INET
        self.state_json = state_json
        self.client_errors = 0
        super().__init__(address, _Handler)

    def handle_error(self, request: Any, client_address: Any) -> None:
        """A client's broken connection: counted, not printed over the status line."""
        self.client_errors += 1


class _Handler(BaseHTTPRequestHandler):
    server: _Server
    timeout = REQUEST_TIMEOUT_S
    server_version = "pilescan-listen"
    sys_version = ""

    def do_GET(self) -> None:
        self._respond(head=False)

    def do_HEAD(self) -> None:
        self._respond(head=True)

    def _respond(self, head: bool) -> None:
        path = urlsplit(self.path).path
        if path in PAGE_PATHS:
            body, ctype = PAGE.encode(), "text/html; charset=utf-8"
        elif path == STATE_PATH:
            body, ctype = self.server.state_json(), "application/json"
        else:
            self.send_error(HTTPStatus.NOT_FOUND, "not a path of this page (/ and /state.json)")
            return
        try:
            self.send_response(HTTPStatus.OK)
            self.send_header("Content-Type", ctype)
            self.send_header("Content-Length", str(len(body)))
            self.send_header("Cache-Control", "no-store")
            self.send_header("Content-Security-Policy", CSP)
            self.send_header("X-Content-Type-Options", "nosniff")
            self.send_header("Referrer-Policy", "no-referrer")
            self.end_headers()
            if not head:
                self.wfile.write(body)
        except (BrokenPipeError, ConnectionResetError, TimeoutError):  # the browser went away mid-response
            self.server.client_errors += 1
            self.close_connection = True

    def log_message(self, format: str, *args: Any) -> None:
        """Requests are not logged: listen's status line owns the terminal."""


class LivePageServer:
    """The page's HTTP server on its own daemon thread. `close()` stops it (idempotent).

    Args:
        host, port: where to bind (port 0: any free port; see `address`).
        state_json: the JSON body of /state.json (called on the server's threads).

    Raises:
        UserError: the address cannot be bound (in use, not of this machine, does not resolve).
    """

    def __init__(self, host: str, port: int, state_json: Callable[[], bytes]) -> None:
        try:
            self._server = _Server((host, port), state_json)
        except (OSError, UnicodeError) as exc:  # in use, not an address here, a name that does not resolve
            raise UserError(f"cannot serve the live page on {host}:{port}: {getattr(exc, 'strerror', None) or exc}"
                            ) from None
        self._thread = threading.Thread(target=self._server.serve_forever, kwargs={"poll_interval": 0.2},
                                        name="live-page", daemon=True)
        self._thread.start()
        self._closed = False

    @property
    def address(self) -> tuple[str, int]:
        host, port = self._server.server_address[:2]
        return str(host), int(port)

    @property
    def url(self) -> str:
        return web_url(*self.address)

    @property
    def client_errors(self) -> int:
        """Connections that broke mid-request or mid-response (browsers closed, networks dropped)."""
        return self._server.client_errors

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5.0)


PAGE = r"""<!doctype html>
<html lang="en">
<head>
<meta charset="utf-8">
<meta name="viewport" content="width=device-width, initial-scale=1">
<title>pilescan live</title>
<style>
  body { font: 15px/1.4 system-ui, "DejaVu Sans", sans-serif; margin: 0; background: #f4f4f2; color: #1d1d1d; }
  header { display: flex; align-items: baseline; gap: 1.5em; padding: 0.6em 1em; background: #1f3a4d; color: #fff; }
  header h1 { font-size: 1.2em; margin: 0; font-weight: 600; }
  #status { padding: 0.15em 0.6em; border-radius: 0.3em; background: #5a6b78; }
  #status.ok { background: #2e7d32; }
  #status.stale, #status.down { background: #c62828; }
  main { display: flex; gap: 1em; padding: 1em; align-items: flex-start; }
  #mapbox { flex: 1 1 auto; min-width: 300px; background: #fff; border: 1px solid #ccc; }
  canvas#map { display: block; width: 100%; }
  aside { flex: 0 0 22em; background: #fff; border: 1px solid #ccc; padding: 0.8em 1em; }
  dl { display: grid; grid-template-columns: auto 1fr; gap: 0.25em 0.8em; margin: 0; }
  dt { color: #555; }
  dd { margin: 0; font-variant-numeric: tabular-nums; }
  dd.big { font-size: 1.35em; font-weight: 600; }
  .note { color: #555; font-size: 0.9em; margin: 0.6em 0 0; }
  #legend { margin-top: 0.8em; }
  #legend canvas { width: 100%; height: 14px; display: block; border: 1px solid #999; }
  #legend .ends { display: flex; justify-content: space-between; font-size: 0.85em; color: #444; }
  .key { display: inline-block; width: 0.9em; height: 0.9em; vertical-align: -0.1em; border: 1px solid #888; }
  @media (max-width: 44em) {  /* a phone: the panel under the map, both the screen's width */
    header { flex-wrap: wrap; gap: 0.5em 1em; }
    main { flex-direction: column; align-items: stretch; padding: 0.5em; }
    #mapbox { min-width: 0; }
    aside { flex: 0 0 auto; }
  }
</style>
</head>
<body>
<header><h1>pilescan &mdash; live survey</h1><span id="status">connecting&hellip;</span></header>
<main>
  <div id="mapbox"><canvas id="map" width="900" height="620" data-draws="0"></canvas></div>
  <aside>
    <dl>
      <dt>Volume</dt><dd id="volume" class="big">&ndash;</dd>
      <dt>90 % interval</dt><dd id="interval">&ndash;</dd>
      <dt>R<sub>a</sub> so far</dt><dd id="ra">&ndash;</dd>
      <dt>Volume from</dt><dd id="volume-age">&ndash;</dd>
      <dt>Records</dt><dd id="records" data-value="0">0</dd>
      <dt>Rate</dt><dd id="rate">&ndash;</dd>
      <dt>Samples</dt><dd id="samples">&ndash;</dd>
      <dt>Datagrams</dt><dd id="datagrams">&ndash;</dd>
      <dt>Lost</dt><dd id="lost">&ndash;</dd>
      <dt>Refused</dt><dd id="refused">&ndash;</dd>
      <dt>Last records</dt><dd id="last">&ndash;</dd>
      <dt>Cells with points</dt><dd id="points">&ndash;</dd>
      <dt>Unseen</dt><dd id="unseen">&ndash;</dd>
    </dl>
    <div id="legend">
      <canvas id="bar" width="256" height="14"></canvas>
      <div class="ends"><span id="zlo">0 m</span><span>height of the points</span><span id="zhi">&ndash;</span></div>
      <p class="note"><span class="key" style="background:#21918c"></span> points &nbsp;
        <span class="key" style="background:#21918c;opacity:0.35"></span> surface between them &nbsp;
        <span class="key" style="background:#d9d9d9"></span> unseen &nbsp;
        <span class="key" style="background:#e8590c"></span> track</p>
    </div>
    <p class="note" id="note"></p>
  </aside>
</main>
<script>
"use strict";
const $ = (id) => document.getElementById(id);
const VIRIDIS = [[68,1,84],[72,40,120],[62,74,137],[49,104,142],[38,130,142],[31,158,137],[53,183,121],
                 [109,205,89],[180,222,44],[253,231,37]];
let polls = 0, lastAnswer = null;

function colour(t, pale = 0) {  // viridis at t in [0, 1]; pale: mixed that much with white
  t = Math.min(1, Math.max(0, t)) * (VIRIDIS.length - 1);
  const i = Math.min(VIRIDIS.length - 2, Math.floor(t)), f = t - i, a = VIRIDIS[i], b = VIRIDIS[i + 1];
  return `rgb(${a.map((v, k) => Math.round((v + f * (b[k] - v)) * (1 - pale) + 255 * pale)).join(",")})`;
}
const fmt = (v, d = 1) => v.toLocaleString("en-US", {minimumFractionDigits: d, maximumFractionDigits: d});
const ago = (s) => s < 90 ? `${fmt(s, 0)} s` : `${fmt(s / 60, 1)} min`;

function setStatus(cls, text) { const e = $("status"); e.className = cls; e.textContent = text; }

function show(s) {
  const c = s.counters, v = s.volume;
  $("records").textContent = fmt(c.records, 0); $("records").dataset.value = c.records;
  $("rate").textContent = c.rate_hz == null ? "\u2013" : `${fmt(c.rate_hz, 0)} /s`;
  $("samples").textContent = c.samples || "\u2013";
  $("datagrams").textContent = fmt(c.datagrams, 0);
  $("lost").textContent = `${fmt(c.lost, 0)} (late ${fmt(c.late, 0)})`;
  $("refused").textContent = fmt(c.refused, 0);
  $("last").textContent = s.since_last_records_s == null ? "none yet" : `${ago(s.since_last_records_s)} ago`;
  if (s.since_last_records_s == null) setStatus("", "waiting for the first datagram");
  else if (s.stale) setStatus("stale", `no data for ${fmt(s.since_last_records_s, 0)} s`);
  else setStatus("ok", "receiving");
  const vol = $("volume"), iv = $("interval");
  if (v.state === "ok") {
    vol.textContent = `${fmt(v.volume_m3)} m\u00b3`; vol.dataset.value = v.volume_m3;
    if (v.interval_m3) {
      iv.textContent = `${fmt(v.interval_m3[0])} \u2013 ${fmt(v.interval_m3[1])} m\u00b3`;
      iv.dataset.lo = v.interval_m3[0]; iv.dataset.hi = v.interval_m3[1];
    } else { iv.textContent = "not estimated"; }
    $("ra").textContent = `${fmt(v.coverage_ratio_pct)} %`;
  } else {
    vol.textContent = {"no-geometry": "no building known", "waiting": "waiting for records",
                       "not-yet": "not yet"}[v.state] || v.state;
    delete vol.dataset.value;
  }
  $("volume-age").dataset.records = v.age_s == null ? 0 : v.records;
  $("volume-age").textContent = v.age_s == null ? "\u2013" :
    `${fmt(v.records, 0)} records, ${ago(v.age_s)} ago` + (v.capped ? " (record cap reached)" : "");
  $("points").textContent = s.map ? `${fmt(s.map.points_pct)} % of ${fmt(s.map.nx * s.map.ny, 0)} cells` : "\u2013";
  $("unseen").textContent = s.map ? `${fmt(s.map.unseen_pct)} %` + (s.map.surface_z_m ? "" : " (no surface yet)")
                                  : "\u2013";
  const notes = [];
  if (s.geometry_problem) notes.push(s.geometry_problem + ": counters and track only (north up, NED).");
  if (v.state === "not-yet" && v.why) notes.push("Volume: " + v.why);
  if (s.worker_error) notes.push("The page's computation met an error and went on: " + s.worker_error + ".");
  notes.push("The volume is the report's computation on the records received so far, without self-calibration"
             + " and servo re-timing; the drone's own log stays the record.");
  $("note").textContent = notes.join(" ");
}

function hatch(ctx) {
  const p = document.createElement("canvas"); p.width = p.height = 8;
  const g = p.getContext("2d"); g.fillStyle = "#e6e6e6"; g.fillRect(0, 0, 8, 8);
  g.strokeStyle = "#b8b8b8"; g.lineWidth = 1.5; g.beginPath(); g.moveTo(0, 8); g.lineTo(8, 0); g.stroke();
  return ctx.createPattern(p, "repeat");
}

function draw(s) {
  const cv = $("map"), box = $("mapbox");
  const W = Math.max(300, Math.floor(box.clientWidth)), pad = 28;
  let x0, x1, y0, y1;  // the view in the plotted frame: x to the right, y up
  const pts = s.track.slice(); if (s.position) pts.push(s.position);
  if (s.storage) { x0 = 0; x1 = s.storage.length_m; y0 = 0; y1 = s.storage.width_m; }
  else {  // NED: north up, east right; plotted x = east, y = north
    const e = pts.map((p) => p[1]), n = pts.map((p) => p[0]);
    x0 = e.length ? Math.min(...e) - 2 : -10; x1 = e.length ? Math.max(...e) + 2 : 10;
    y0 = n.length ? Math.min(...n) - 2 : -10; y1 = n.length ? Math.max(...n) + 2 : 10;
  }
  const scale = (W - 2 * pad) / (x1 - x0), H = Math.round((y1 - y0) * scale + 2 * pad);
  if (cv.width !== W || cv.height !== H) { cv.width = W; cv.height = H; }
  const X = (x) => pad + (x - x0) * scale, Y = (y) => H - pad - (y - y0) * scale;
  const P = s.storage ? (p) => [X(p[0]), Y(p[1])] : (p) => [X(p[1]), Y(p[0])];
  const ctx = cv.getContext("2d");
  ctx.fillStyle = "#fff"; ctx.fillRect(0, 0, W, H);
  let points = 0, between = 0, unseen = 0, zmax = 0;
  if (s.map) {
    const m = s.map, c = m.cell_m, dx = s.storage.length_m / m.nx, dy = s.storage.width_m / m.ny;
    const zs = m.z_m.filter((z) => z != null).sort((a, b) => a - b);
    zmax = Math.max(1, zs.length ? zs[Math.floor(0.98 * (zs.length - 1))] : 0);  // a few stray cells do not set it
    const unseenFill = hatch(ctx), surf = m.surface_z_m;
    for (let i = 0; i < m.nx; i++) for (let j = 0; j < m.ny; j++) {
      const k = i * m.ny + j, z = m.z_m[k], zs = surf ? surf[k] : null;
      if (z != null) { ctx.fillStyle = colour(z / zmax); points++; }
      else if (zs != null) { ctx.fillStyle = colour(zs / zmax, 0.65); between++; }
      else { ctx.fillStyle = unseenFill; unseen++; }
      ctx.fillRect(X(i * dx), Y((j + 1) * dy), dx * scale + 0.6, dy * scale + 0.6);
    }
    ctx.strokeStyle = "#111"; ctx.lineWidth = 2; ctx.strokeRect(X(0), Y(s.storage.width_m),
      s.storage.length_m * scale, s.storage.width_m * scale);
    ctx.fillStyle = "#333"; ctx.font = "12px sans-serif";
    ctx.fillText(`${fmt(s.storage.length_m, 0)} m \u00d7 ${fmt(s.storage.width_m, 0)} m, cells of ${fmt(c, 2)} m`,
                 X(0), Y(s.storage.width_m) - 8);
    ctx.fillText("x", X(s.storage.length_m) - 8, Y(0) + 16); ctx.fillText("y", X(0) - 14, Y(s.storage.width_m) + 10);
  } else {
    ctx.fillStyle = "#333"; ctx.font = "12px sans-serif"; ctx.fillText("N \u2191  (NED, no building known)", 8, 16);
  }
  ctx.strokeStyle = "#e8590c"; ctx.lineWidth = 2; ctx.lineJoin = "round"; ctx.beginPath();
  s.track.forEach((p, k) => { const q = P(p); if (k) ctx.lineTo(q[0], q[1]); else ctx.moveTo(q[0], q[1]); });
  ctx.stroke();
  if (s.position) {
    const q = P(s.position);
    ctx.fillStyle = "#e8590c"; ctx.strokeStyle = "#fff"; ctx.lineWidth = 2;
    ctx.beginPath(); ctx.arc(q[0], q[1], 7, 0, 2 * Math.PI); ctx.fill(); ctx.stroke();
    if (s.course_rad != null) {  // W: anticlockwise from x; NED: clockwise from north
      const a = s.storage ? s.course_rad : Math.PI / 2 - s.course_rad;
      ctx.strokeStyle = "#111"; ctx.beginPath(); ctx.moveTo(q[0], q[1]);
      ctx.lineTo(q[0] + 18 * Math.cos(a), q[1] - 18 * Math.sin(a)); ctx.stroke();
    }
  }
  $("zhi").textContent = s.map ? `${fmt(zmax, 1)} m` : "\u2013";
  cv.dataset.cellsPoints = points; cv.dataset.cellsBetween = between; cv.dataset.cellsUnseen = unseen;
  cv.dataset.trackPoints = s.track.length;
  cv.dataset.draws = Number(cv.dataset.draws) + 1;
}

function legend() {
  const b = $("bar"), g = b.getContext("2d");
  for (let i = 0; i < b.width; i++) { g.fillStyle = colour(i / (b.width - 1)); g.fillRect(i, 0, 1, b.height); }
}

async function poll() {
  try {
    const r = await fetch("state.json", {cache: "no-store"});
    if (!r.ok) throw new Error(`HTTP ${r.status}`);
    const s = await r.json();
    lastAnswer = Date.now(); polls++;
    show(s); draw(s);
    document.documentElement.dataset.polls = polls;
  } catch (e) {
    const since = lastAnswer == null ? "" : `; last answer ${ago((Date.now() - lastAnswer) / 1000)} ago`;
    setStatus("down", `the ground station does not answer${since}`);
  } finally {
    setTimeout(poll, 1000);
  }
}
legend();
poll();
</script>
</body>
</html>
"""
