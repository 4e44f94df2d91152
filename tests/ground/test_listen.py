"""`pilescan-ground listen`: a real LiveStreamSender to the listener over localhost UDP, in-process; records land
intact in a sample log; unauthenticated, forged, replayed and disallowed datagrams are refused and counted."""

from __future__ import annotations

import contextlib
import io
import json
import os
import signal
import socket
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.cli import UserError
from firmware_py.core.keys import signing_timestamp
from firmware_py.core.samplelog import SampleLogWriter, read_samplelog
from firmware_py.core.stream_format import encode_datagram
from firmware_py.live_stream import LiveStreamSender
from ground.cli import main
from ground.listen import (
    CONFIRM_RUN,
    GEOMETRY_KEYS,
    LIVE_SOURCE,
    JoiningReceiver,
    ListenConfig,
    Listener,
    format_summary,
    load_header,
    parse_peer,
)
from ground.live_receiver import DEFAULT_MAX_RATE_HZ, LOSS_GRACE_S
from tests.firmware_py.test_live_stream import records
from tests.ground.test_report_fuzz import BASE_HEADER

KEY = bytes(range(1, 33))
OTHER = bytes(range(2, 34))




@contextlib.contextmanager
def listening(tmp_path: Path, **kw):
    """An open Listener on a free localhost port, writing tmp_path/live.pslog; closed on exit."""
    cfg = ListenConfig(url="udp:127.0.0.1:0", out_path=tmp_path / "live.pslog", fsync=False, **kw)
    listener = Listener(cfg, err=io.StringIO())
    listener.open()
    try:
        yield listener
    finally:
        listener.close()


def url_of(listener: Listener) -> str:
    return f"udp:127.0.0.1:{listener.local_address[1]}"


def pump_until(listener: Listener, done, timeout_s: float = 5.0) -> None:
    """Take datagrams until done(stats) holds (or give up: the assertions after say what is missing)."""
    deadline = time.monotonic() + timeout_s
    while not done(listener.rx.stats) and time.monotonic() < deadline:
        listener.pump(0.05)


def send(url: str, recs: np.ndarray, **kw) -> LiveStreamSender:
    tx = LiveStreamSender(url, **kw)
    tx.append(recs)
    tx.close()
    return tx


def test_that_unsigned_records_arrive_intact_in_a_readable_log(tmp_path):
    sent = records(125)
    with listening(tmp_path) as ls:
        send(url_of(ls), sent)
        pump_until(ls, lambda st: st["records"] >= 125)
        res = ls.result()
    log = read_samplelog(tmp_path / "live.pslog")
    assert log.intact and log.samples.tobytes() == sent.tobytes()
    assert log.header["source"] == LIVE_SOURCE and log.header["live_stream"]["authenticated"] is False
    assert res.records == 125 and res.flagged == int(np.count_nonzero(sent["flags"]))
    assert res.stats["datagrams"] == 7 and res.refused == {} and res.warnings == ()


def test_that_signed_records_arrive_and_unauthenticated_forged_and_replayed_ones_are_refused(tmp_path):
    good, forged, plain = records(60), records(40, t0=100.0), records(20, t0=200.0)
    with listening(tmp_path, key=KEY) as ls:
        url = url_of(ls)
        port = ls.local_address[1]
        send(url, forged, key=OTHER)  # another key: bad tags
        send(url, plain)  # no key: version 1, unauthenticated
        send(url, good, key=KEY)
        replay = encode_datagram(7, records(3, t0=300.0), key=KEY, stamp=signing_timestamp(time.time()),
                                 sender_id=9)
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.sendto(replay, ls.local_address)
            s.sendto(replay, ls.local_address)  # captured and played again
        pump_until(ls, lambda st: st["records"] >= 63 and st["bad_tag"] >= 2 and st["unauthenticated"] >= 1
                   and st["replayed"] >= 1)
        res = ls.result()
    assert res.refused == {"bad_tag": 2, "unauthenticated": 1, "replayed": 1}
    samples = read_samplelog(tmp_path / "live.pslog").samples
    assert len(samples) == 63 and set(np.floor(samples["t_s"] / 100)) == {0.0, 3.0}  # none refused got in
    assert samples[np.argsort(samples["t_s"], kind="stable")][:60].tobytes() == good.tobytes()
    summary = format_summary(res)
    assert res.authenticated and "refused       4 (unauthenticated 1, bad_tag 2, replayed 1)" in summary
    assert f"on udp:127.0.0.1:{port} (authenticated)" in summary  # the port it got


def test_that_only_allowed_peers_are_heard(tmp_path):
    allowed = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    allowed.bind(("127.0.0.1", 0))
    with listening(tmp_path, allowed_peers=(("127.0.0.1", allowed.getsockname()[1]),)) as ls:
        url = url_of(ls)
        send(url, records(30, t0=50.0))  # its own socket, another port
        send(url, records(10), sock=allowed)
        pump_until(ls, lambda st: st["records"] >= 10 and st["rejected_peer"] >= 2)
        res = ls.result()
    assert res.refused == {"rejected_peer": 2} and res.records == 10
    assert np.all(read_samplelog(tmp_path / "live.pslog").samples["t_s"] < 50.0)
    assert "not an allowed peer" in res.last_refusal


def test_that_a_header_file_is_written_with_the_live_stream_noted(tmp_path):
    src = tmp_path / "setup.pslog"
    with SampleLogWriter(src, BASE_HEADER, fsync=False):
        pass
    header = load_header(src)
    assert "record_dtype" not in header and header["storage"] == BASE_HEADER["storage"]
    with listening(tmp_path, header=header, header_from=str(src)) as ls:
        send(url_of(ls), records(5))
        pump_until(ls, lambda st: st["records"] >= 5)
    log = read_samplelog(tmp_path / "live.pslog")
    assert {k: log.header[k] for k in BASE_HEADER} == BASE_HEADER  # what the report needs, unchanged
    assert log.header["live_stream"]["header_from"] == str(src) and len(log.samples) == 5
    as_json = tmp_path / "header.json"
    as_json.write_text(json.dumps(BASE_HEADER))
    assert load_header(as_json) == BASE_HEADER


@pytest.mark.parametrize(("content", "words"), [
    (b"", "neither a sample log"),
    (b"\xff\xfe not text", "neither a sample log"),
    (b"[1, 2]", "JSON object"),
    (b'{"record_dtype": [["t_s", "<f8"]]}', "another layout"),
    (b'{"format": "other-log"}', "another format"),
    (b"PSLB and then nothing", "missing or corrupt"),
])
def test_that_a_bad_header_file_is_a_one_line_user_error(tmp_path, content, words):
    path = tmp_path / "h"
    path.write_bytes(content)
    with pytest.raises(UserError, match=words) as excinfo:
        load_header(path)
    assert str(path) in str(excinfo.value) and "\n" not in str(excinfo.value)


@pytest.mark.parametrize(("text", "peer"), [
    ("10.0.0.5", "10.0.0.5"), ("10.0.0.5:14600", ("10.0.0.5", 14600)), ("drone.local", "drone.local"),
    ("::1", "::1"), ("[::1]", "::1"), ("[fe80::1]:9", ("fe80::1", 9)),
])
def test_that_peers_parse(text, peer):
    assert parse_peer(text) == peer


@pytest.mark.parametrize("text", ["", " ", ":80", "h:", "h:0", "h:65536", "h:x", "[::1", "[::1]x", "[]:5", "a b"])
def test_that_bad_peers_are_value_errors(text):
    with pytest.raises(ValueError, match="allowed peer"):
        parse_peer(text)


# ----- the command, end to end: status lines, a clean stop on SIGTERM, the summary ------------------------

def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_that_the_command_logs_a_signed_stream_until_sigterm(tmp_path, capsys):
    port, out = free_port(), tmp_path / "live.pslog"
    key = tmp_path / "link.key"
    key.write_text(KEY.hex() + "\n")
    key.chmod(0o600)
    sent = records(200)
    listening_done = threading.Event()
    outcome = {}

    def payload() -> None:
        """Stream once the listener is up, wait until its log holds everything, then stop it like Ctrl-C would.

        Nothing here waits on a clock: the listener creates its log only after binding its socket, and
        writes received records only right after a status line; so once the log holds every record, a
        status line counting every datagram has been printed, however slow the machine.
        """
        while not out.exists() and not listening_done.is_set():
            time.sleep(0.01)
        if listening_done.is_set():
            return  # it never came up: the assertions on rc say why
        send(f"udp:127.0.0.1:{port}", sent, key=KEY)
        send(f"udp:127.0.0.1:{port}", records(20, t0=100.0), key=OTHER)
        while not listening_done.is_set() and len(read_samplelog(out).samples) < len(sent):
            time.sleep(0.05)
        outcome["logged_while_listening"] = len(read_samplelog(out).samples)
        os.kill(os.getpid(), signal.SIGTERM)  # if the listener has just ended, the test's handler takes it

    previous = signal.signal(signal.SIGTERM, lambda *_: None)  # a late SIGTERM must not end the test run
    thread = threading.Thread(target=payload)
    thread.start()
    try:  # --duration only ends a listener the signal never reached (the test then fails on "stopped")
        rc = main(["listen", "--stream", f"udp:127.0.0.1:{port}", "--signing-key", str(key), "--out", str(out),
                   "--duration", "120"])
    finally:
        listening_done.set()
        thread.join()
        signal.signal(signal.SIGTERM, previous)
    cap = capsys.readouterr()
    assert rc == 0, cap.err
    assert outcome.get("logged_while_listening") == len(sent)  # on disk within a status period, not at close
    assert "stopped       signal SIGTERM" in cap.out and "refused       1 (bad_tag 1)" in cap.out
    assert f"records       {len(sent)} " in cap.out and " in 10 datagrams" in cap.out
    assert "pilescan-ground listen: " in cap.err and "datagrams 10" in cap.err  # a status line
    log = read_samplelog(out)
    assert log.intact and log.samples.tobytes() == sent.tobytes()
    assert log.header["live_stream"]["authenticated"] is True


def test_that_a_port_in_use_is_one_line_and_exit_4(tmp_path, capsys):
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as taken:
        taken.bind(("127.0.0.1", 0))
        port = taken.getsockname()[1]
        rc = main(["listen", "--stream", f"udp:127.0.0.1:{port}", "--out", str(tmp_path / "x.pslog")])
    err = capsys.readouterr().err
    assert rc == 4 and err.count("\n") == 1 and "Traceback" not in err  # ExitCode.RUNTIME: the system refused
    assert f"cannot listen on udp:127.0.0.1:{port}" in err and "in use" in err
    assert not (tmp_path / "x.pslog").exists()  # nothing written for a port it could not have


def test_that_a_timed_listen_with_nothing_arriving_ends_with_a_warning(tmp_path, capsys):
    rc = main(["listen", "--stream", f"udp:127.0.0.1:{free_port()}", "--duration", "0.2"])
    cap = capsys.readouterr()
    assert rc == 0 and "stopped       duration reached" in cap.out
    assert "WARNING: no datagrams accepted" in cap.out and "log           none (no --out)" in cap.out


# ----- hostile senders: forged sequence numbers, floods, what the records are ---------------------------

def test_that_forged_sequence_numbers_from_another_sender_are_resyncs_not_losses(tmp_path):
    """A forger's jumps of a billion datagrams (the old count reached 80,989,069,990,385) cannot make the
    payload's stream look lossy: loss is counted per sender, within what a sender could have sent."""
    with listening(tmp_path) as ls, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as forger:
        url = url_of(ls)
        payload = LiveStreamSender(url, records_per_datagram=10)
        for k in range(4):
            payload.append(records(10, t0=float(k)))
            forger.sendto(encode_datagram(k * 1_000_000_000, records(1, t0=900.0)), ls.local_address)
        payload.close()
        pump_until(ls, lambda st: st["datagrams"] >= 8)
        res = ls.result()
    assert res.stats["datagrams"] == 8 and res.stats["lost"] == 0
    assert res.stats["resyncs"] == 3 and res.stats["senders"] == 2
    assert "implausible sequence jumps 3 (not counted as lost); from 2 senders" in format_summary(res)


def test_that_a_plausible_gap_is_still_counted_as_lost_for_its_sender():
    from ground.live_receiver import LiveStreamReceiver
    rx = LiveStreamReceiver()
    for seq in (0, 1, 5, 6):  # 2, 3 and 4 lost
        rx.feed(encode_datagram(seq, records(1)), ("10.0.0.2", 5000))
    for seq in (0, 1, 2):  # another sender, from 0: neither a restart nor late
        rx.feed(encode_datagram(seq, records(1)), ("10.0.0.3", 5000))
    assert (rx.stats["lost"], rx.stats["restarts"], rx.stats["late"], rx.stats["resyncs"]) == (3, 0, 0, 0)
    assert rx.sender_losses() == {(("10.0.0.2", 5000), None): (4, 3), (("10.0.0.3", 5000), None): (3, 0)}


def test_that_the_sender_table_is_bounded_under_a_flood_of_source_ports():
    from ground.live_receiver import MAX_SENDERS, LiveStreamReceiver
    rx = LiveStreamReceiver()
    for port in range(1, 3 * MAX_SENDERS + 1):
        rx.feed(encode_datagram(port * 7, records(1)), ("127.0.0.1", port))
    assert rx.stats["senders"] == MAX_SENDERS and rx.stats["senders_evicted"] == 2 * MAX_SENDERS
    assert len(rx.sender_losses()) == MAX_SENDERS


def test_that_the_log_stops_at_its_size_cap_whole_and_says_so_once(tmp_path):
    per_block = 20
    err = io.StringIO()
    cfg = ListenConfig(url="udp:127.0.0.1:0", out_path=tmp_path / "live.pslog", fsync=False,
                       records_per_block=per_block, max_log_bytes=4096)
    ls = Listener(cfg, err=err)
    ls.open()
    try:
        url = url_of(ls)
        for k in range(10):
            send(url, records(20, t0=float(k)))
            pump_until(ls, lambda st, k=k: st["records"] >= 20 * (k + 1))
            ls.log.flush()  # as each status period does: short blocks too
    finally:
        ls.close()
    res = ls.result()
    size = (tmp_path / "live.pslog").stat().st_size
    log = read_samplelog(tmp_path / "live.pslog")
    assert size <= 4096 and log.intact and 0 < len(log.samples) < 200
    assert res.records == 200 and res.records_unlogged == 200 - len(log.samples)
    assert err.getvalue().count("size cap of") == 1 and "--max-log-mb" in err.getvalue()
    assert f"{res.records_unlogged} records received but not written" in format_summary(res)


def test_that_the_summary_says_no_returns_are_no_returns_not_faults(tmp_path):
    sent = records(40)
    sent["flags"] = 1  # NO_RETURN: nothing in range, all of them
    with listening(tmp_path) as ls:
        send(url_of(ls), sent)
        pump_until(ls, lambda st: st["records"] >= 40)
        res = ls.result()
        line = ls.status_line(ls.clock())
    assert "records       40 in 2 datagrams" in format_summary(res)
    assert ": usable 0, no return 40, faulty 0" in format_summary(res)
    assert "usable 0, no return 40, faulty 0" in line and "flagged" not in format_summary(res)


@pytest.mark.parametrize("value", ["0", "-5", "nan"])
def test_that_a_bad_log_size_cap_is_one_line_and_exit_2(tmp_path, capsys, value):
    rc = main(["listen", "--stream", "udp:127.0.0.1:14600", "--out", str(tmp_path / "x.pslog"),
               "--max-log-mb", value])
    err = capsys.readouterr().err
    assert rc == 2 and "--max-log-mb" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "x.pslog").exists()


def test_that_a_live_log_removed_under_the_listener_is_no_traceback(tmp_path):
    with listening(tmp_path) as ls:
        (tmp_path / "live.pslog").unlink()
        send(url_of(ls), records(30))
        pump_until(ls, lambda st: st["records"] >= 30)
        assert ls.records == 30


@pytest.mark.parametrize("kind", ["fifo", "dir"])
def test_that_a_header_file_that_is_not_a_regular_file_is_refused_at_once(tmp_path, kind):
    path = tmp_path / "h"
    os.mkfifo(path) if kind == "fifo" else path.mkdir()
    with pytest.raises(UserError, match="not a regular file") as excinfo:
        load_header(path)  # a FIFO with no writer would block a plain read for ever
    assert "\n" not in str(excinfo.value)


# ----- joining a stream already under way (listen started after the payload) ----------------------------

def test_that_a_listener_first_hearing_record_300_says_so_and_counts_the_300_before_as_lost(tmp_path):
    """The networked-SITL report: records 0-299 never arrived and listen said "lost 0". The datagrams are
    numbered from 0, so the first one heard, number 15 (records 300-319), says 15 were sent before."""
    with listening(tmp_path) as ls, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as payload:
        for seq in range(15, 15 + CONFIRM_RUN + 6):  # the stream goes on from there, one number at a time
            payload.sendto(encode_datagram(seq, records(20, t0=seq * 0.04)), ls.local_address)
        pump_until(ls, lambda st: st["records"] >= 20 * (CONFIRM_RUN + 6))
        status = ls.status_line(ls.clock())
        res = ls.result()
        said = ls.err.getvalue()
    assert res.records == 20 * (CONFIRM_RUN + 6) and res.stats["joined"] == 15 and res.stats["lost"] == 15
    assert "lost 15 " in status
    assert said.count("joined the stream from 127.0.0.1:") == 1
    assert "at datagram 15 (about record 300): the 15 datagrams sent before it, up to 300 records" in said
    summary = format_summary(res)
    assert "lost          15 datagrams (15 sent before listen joined, 0 in transit; late 0" in summary
    assert "joined        at datagram 15 of the stream from 127.0.0.1:" in summary
    assert "15 earlier datagrams, up to 300 records, not received" in summary


def test_that_a_listener_started_after_the_payload_counts_what_the_payload_sent_before(tmp_path):
    """The cause: UDP keeps no history, so a listener started after the payload's first 300 records never
    gets them; the sender numbers its datagrams from 0 whether or not anyone listens, and listen counts them."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    sent = records(300 + 20 * (CONFIRM_RUN + 5))
    tx = LiveStreamSender(f"udp:127.0.0.1:{port}")  # 20 records a datagram, as the payload
    tx.append(sent[:300])  # nobody listening yet: 15 datagrams into the void, no error
    cfg = ListenConfig(url=f"udp:127.0.0.1:{port}", out_path=tmp_path / "live.pslog", fsync=False)
    ls = Listener(cfg, err=io.StringIO())
    ls.open()
    try:
        tx.append(sent[300:])
        tx.close()
        pump_until(ls, lambda st: st["records"] >= len(sent) - 300)
    finally:
        ls.close()
    res = ls.result()
    assert tx.stats["datagrams"] == len(sent) // 20 and tx.stats["send_errors"] == 0
    assert read_samplelog(tmp_path / "live.pslog").samples.tobytes() == sent[300:].tobytes()
    assert res.records == len(sent) - 300 and res.stats["lost"] == 15 and res.stats["joined"] == 15
    assert "up to 300 records, not received" in format_summary(res)


def test_that_a_stream_heard_from_its_first_datagram_says_nothing_of_joining(tmp_path):
    with listening(tmp_path) as ls:
        send(url_of(ls), records(60))
        pump_until(ls, lambda st: st["records"] >= 60)
        res = ls.result()
        said = ls.err.getvalue()
    assert res.stats["lost"] == 0 and res.stats["joined"] == 0 and res.joins == ()
    assert "joined" not in format_summary(res) and "joined" not in said


def test_that_a_forged_first_number_or_a_flood_of_random_ones_adds_nothing_and_a_real_run_is_counted():
    # listen's flood campaign: random numbers from two ports made 5,984 "lost" datagrams of a 249-datagram stream
    rng = np.random.default_rng(0)
    rx = JoiningReceiver()
    rx.feed(encode_datagram(4_000_000_000, records(1)), ("10.0.0.9", 4000))
    for _ in range(500):
        rx.feed(encode_datagram(int(rng.integers(1 << 32)), records(1)), ("10.0.0.9", 4001))
    assert rx.stats["joined"] == 0 and rx.joined() == ()
    for seq in range(40, 40 + CONFIRM_RUN + 1):  # a payload's stream: one number at a time
        rx.feed(encode_datagram(seq, records(20)), ("10.0.0.2", 5000))
    assert rx.stats["joined"] == 40 and [j.first_seq for j in rx.joined()] == [40]


def test_that_a_stream_joined_an_hour_in_is_counted_in_full_once_heard_long_enough_to_vouch_for_it():
    now = [0.0]
    rx = JoiningReceiver(monotonic=lambda: now[0])
    first = 25 * 3600  # 20-record datagrams at 500 Hz, an hour in
    for seq in range(first, first + CONFIRM_RUN + 1):
        rx.feed(encode_datagram(seq, records(20)), ("10.0.0.2", 5000))
    assert rx.stats["joined"] == int(DEFAULT_MAX_RATE_HZ * LOSS_GRACE_S) < first  # a second's worth so far
    now[0] = 60.0
    last = first + CONFIRM_RUN + 1500
    rx.feed(encode_datagram(last, records(20)), ("10.0.0.2", 5000))
    assert rx.stats["joined"] == first and rx.stats["lost"] == first + 1499


def test_that_a_datagram_reordered_behind_the_first_one_heard_is_not_counted_as_missed():
    rx = JoiningReceiver()
    rx.feed(encode_datagram(16, records(20)), ("10.0.0.2", 5000))
    rx.feed(encode_datagram(15, records(20)), ("10.0.0.2", 5000))  # late: it was sent first
    for seq in range(17, 17 + CONFIRM_RUN + 1):
        rx.feed(encode_datagram(seq, records(20)), ("10.0.0.2", 5000))
    assert rx.stats["joined"] == rx.stats["lost"] == 15 and rx.stats["late"] == 1
    assert rx.joined()[0].first_seq == 15 and rx.joined()[0].records_max == 300


def test_that_the_header_the_payload_s_check_writes_gives_the_live_log_its_geometry(tmp_path):
    # pilescan-payload --check --write-header: the header a first flight's live log can have before any flight
    from firmware_py.cli import main as payload_main
    example = Path(__file__).resolve().parents[2] / "examples" / "raspberry-pi.toml"
    out = tmp_path / "setup.json"
    assert payload_main(["--config", str(example), "--out", str(tmp_path / "f.pslog"), "--check",
                         "--write-header", str(out)]) == 0
    header = load_header(out)
    assert not [k for k in GEOMETRY_KEYS if k not in header]
