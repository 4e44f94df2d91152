"""`listen --web`: the page and /state.json served on an ephemeral port and fetched with urllib; its own paths
only, a browser that hangs up mid-response, bad addresses (one line, exit 2), and a Listener feeding it."""

from __future__ import annotations

import io
import json
import re
import socket
import struct
import time
import urllib.error
import urllib.request

import pytest

from firmware_py.core.cli import ExitCode, UserError
from firmware_py.core.samplelog import read_samplelog
from firmware_py.live_stream import LiveStreamSender
from ground.cli import main
from ground.listen import ListenConfig, Listener, format_summary, load_header
from ground.live_page import CSP, PAGE, LivePageServer, parse_web_address, web_url
from tests.ground.test_live_state import GOLDEN


def get(url: str, method: str = "GET") -> tuple[int, dict, bytes]:
    req = urllib.request.Request(url, method=method)
    try:
        with urllib.request.urlopen(req, timeout=10) as r:
            return r.status, dict(r.headers), r.read()
    except urllib.error.HTTPError as exc:
        return exc.code, dict(exc.headers), exc.read()


@pytest.fixture
def server():
    srv = LivePageServer("127.0.0.1", 0, lambda: b'{"ok":true}')
    yield srv
    srv.close()


def test_that_the_page_and_its_json_are_served_with_a_policy_that_lets_nothing_in(server):
    status, headers, body = get(server.url)
    assert status == 200 and headers["Content-Type"].startswith("text/html") and body == PAGE.encode()
    assert headers["Content-Security-Policy"] == CSP and "connect-src 'self'" in CSP
    status, headers, body = get(server.url + "state.json")
    assert status == 200 and headers["Content-Type"] == "application/json" and json.loads(body) == {"ok": True}
    assert headers["Cache-Control"] == "no-store"
    status, headers, body = get(server.url + "state.json", method="HEAD")
    assert status == 200 and body == b"" and headers["Content-Length"] == "11"


def test_that_the_page_fetches_nothing_from_outside():
    assert not re.search(r"(https?:)?//[a-z0-9]", PAGE.replace("http://www.w3.org", ""), flags=re.I)
    assert not re.search(r"<(link|img|iframe|object|embed)\b|\bsrc=|@import|url\(", PAGE, flags=re.I)
    assert 'fetch("state.json"' in PAGE  # relative: its own server


@pytest.mark.parametrize("path", ["/etc/passwd", "/../state.json.bak", "/state.json/x", "/index.htm", "//x",
                                  "/static/app.js"])
def test_that_only_its_own_paths_are_served(server, path):
    status, _, _ = get(server.url.rstrip("/") + path)
    assert status == 404


def test_that_other_methods_are_refused(server):
    status, _, _ = get(server.url + "state.json", method="POST")
    assert status == 501


def test_that_a_browser_hanging_up_mid_response_costs_nothing_but_its_connection():
    big = b"[" + b"0," * (16 << 20) + b"0]"  # 32 MiB: more than any socket buffer holds
    srv = LivePageServer("127.0.0.1", 0, lambda: big)
    try:
        s = socket.create_connection(srv.address, timeout=10)
        s.sendall(b"GET /state.json HTTP/1.1\r\nHost: x\r\n\r\n")
        head = b""
        while len(head) < 12:
            head += s.recv(4096)
        assert head.startswith(b"HTTP/1.0 200")
        s.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        s.close()  # a reset, mid-body
        deadline = time.monotonic() + 30
        while srv.client_errors == 0 and time.monotonic() < deadline:
            time.sleep(0.05)
        assert srv.client_errors == 1
        status, _, body = get(srv.url + "state.json")  # and it still serves
        assert status == 200 and len(body) == len(big)
    finally:
        srv.close()


def test_that_close_releases_the_port():
    srv = LivePageServer("127.0.0.1", 0, lambda: b"{}")
    addr = srv.address
    srv.close()
    srv.close()  # idempotent
    with pytest.raises(OSError):
        socket.create_connection(addr, timeout=2).close()


@pytest.mark.parametrize(("text", "want"), [("127.0.0.1:8080", ("127.0.0.1", 8080)),
                                            (" localhost:0 ", ("localhost", 0)), ("[::1]:8081", ("::1", 8081))])
def test_that_web_addresses_parse(text, want):
    assert parse_web_address(text) == want


@pytest.mark.parametrize("text", ["8080", "127.0.0.1", "127.0.0.1:", ":8080", "127.0.0.1:65536", "127.0.0.1:-1",
                                  "127.0.0.1:80a", "::1:8080", "[::1]8080", "a b:80", "http://x:80", "x:８０"])
def test_that_bad_web_addresses_are_one_line_errors(text):
    with pytest.raises(ValueError) as exc:
        parse_web_address(text)
    assert "\n" not in str(exc.value)


def test_that_web_url_brackets_ipv6():
    assert web_url("::1", 80) == "http://[::1]:80/" and web_url("127.0.0.1", 80) == "http://127.0.0.1:80/"


def test_that_a_port_in_use_is_a_user_error():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        with pytest.raises(UserError, match=r"cannot serve the live page on 127\.0\.0\.1:.*in use") as exc:
            LivePageServer("127.0.0.1", busy.getsockname()[1], lambda: b"{}")
    assert "\n" not in str(exc.value)


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.parametrize(("web", "code"), [("127.0.0.1:99999", ExitCode.USAGE), ("nonsense", ExitCode.USAGE),
                                           ("busy", ExitCode.RUNTIME), ("192.0.2.1:8080", ExitCode.RUNTIME)])
def test_that_listen_refuses_a_bad_web_address_in_one_line(capsys, tmp_path, web, code):
    """A malformed address is a bad command line (2); one the system refuses, in use or not of this machine, is
    exit 4, as listen's own UDP port in use is (`firmware_py.core.cli.exit_code_of`). Nothing is written."""
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        if web == "busy":
            web = f"127.0.0.1:{busy.getsockname()[1]}"
        got = main(["listen", "--stream", f"udp:127.0.0.1:{free_udp_port()}", "--web", web, "--duration", "0.5",
                    "--out", str(tmp_path / "live.pslog")])
    err = capsys.readouterr().err
    assert got == code and len(err.strip().splitlines()) == 1 and "Traceback" not in err
    assert "--web" in err or "cannot serve the live page" in err
    assert not (tmp_path / "live.pslog").exists()


def test_that_a_listener_serves_its_counters_map_and_volume_on_its_page(tmp_path):
    header = load_header(GOLDEN / "samples.pslog")
    samples = read_samplelog(GOLDEN / "samples.pslog").samples
    cfg = ListenConfig(url="udp:127.0.0.1:0", header=header, header_from="golden", web=("127.0.0.1", 0),
                       out_path=tmp_path / "live.pslog", fsync=False)
    err = io.StringIO()
    ls = Listener(cfg, err=err)
    ls.open()
    try:
        assert f"live page on {ls.page.url}" in err.getvalue()
        for i in range(0, len(samples), 100):  # paced, so the loopback's buffer never overflows
            tx = LiveStreamSender(f"udp:127.0.0.1:{ls.local_address[1]}")
            tx.append(samples[i:i + 100])
            tx.close()
            ls.pump(0.05)
        deadline = time.monotonic() + 20
        while ls.records < len(samples) and time.monotonic() < deadline:
            ls.pump(0.05)
        assert ls.records == len(samples)
        deadline = time.monotonic() + 60  # the page's own threads: the volume within a few seconds
        while True:
            status, _, body = get(ls.page.url + "state.json")
            s = json.loads(body)
            if s["volume"]["records"] == len(samples) or time.monotonic() > deadline:
                break
            time.sleep(0.2)
        assert status == 200 and s["counters"]["records"] == len(samples)
        assert s["counters"]["datagrams"] == ls.rx.stats["datagrams"] and s["counters"]["lost"] == 0
        report_m3 = json.loads((GOLDEN / "report_figures.json").read_text())["volume_m3"]  # the golden log's report
        assert s["volume"]["state"] == "ok" and s["volume"]["volume_m3"] == pytest.approx(report_m3, abs=0.01)
        assert s["map"]["points_pct"] > 10 and len(s["track"]) > 100
    finally:
        ls.close()
    res = ls.result()
    assert res.web_url == ls.page.url and f"live page     {res.web_url}" in format_summary(res)
    with pytest.raises(OSError):
        socket.create_connection(ls.page.address, timeout=2).close()  # closed with the listener


def test_that_a_listener_without_a_header_says_so_on_its_page():
    cfg = ListenConfig(url="udp:127.0.0.1:0", web=("127.0.0.1", 0))
    ls = Listener(cfg, err=None)
    ls.open()
    try:
        s = json.loads(get(ls.page.url + "state.json")[2])
        assert s["frame"] == "ned" and s["map"] is None and "no --header" in s["geometry_problem"]
        assert s["volume"]["state"] == "no-geometry"
    finally:
        ls.close()


def test_that_on_a_phone_the_live_page_stacks_its_panel_under_the_map(tmp_path):
    # side by side, the panel was cut off ("Volum", "R_a so") and the page 694 px wide on a 390 px screen
    import re

    from tools.report_screenshot import find_chromium, render
    if find_chromium() is None:
        pytest.skip("no Chromium installed (apt-get install chromium; .ci/run installs it)")
    probe = ('<script>window.addEventListener("load", function () { var h = document.documentElement;'
             ' h.setAttribute("data-page-width", String(h.scrollWidth));'
             ' h.setAttribute("data-view-width", String(window.innerWidth)); });</script></body>')
    page = tmp_path / "live.html"
    page.write_text(PAGE.replace("</body>", probe))
    dom = render(page, window_px=(390, 1200)).dom
    width, view = (int(re.search(rf'data-{k}-width="(\d+)"', dom).group(1)) for k in ("page", "view"))
    assert width <= view
