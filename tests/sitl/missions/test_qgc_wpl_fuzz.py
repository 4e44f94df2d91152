"""Fuzzing the mission plan files we read: our QGC WPL 110 reader (`read_qgc_wpl`) and the scripted ground
station's loader (`sitl.mavlink.gcs.load_plan`, pymavlink's mavwp underneath). Random or garbled files give a ValueError
(GcsError for the loader) naming the file, never another exception; a file either loads whole or not at all.
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, assume, given
from hypothesis import strategies as st

from tests.fuzz_budget import budget

os.environ["MAVLINK20"] = "1"  # as the networked SITL's ground station runs (MISSION_ITEM_INT, MAVLink 2)

from firmware_py.core.frames import StorageFrame
from firmware_py.core.storage import Storage
from sitl.mavlink.gcs import GcsError, load_plan
from sitl.missions.qgc_wpl import plan_rows, read_qgc_wpl, write_qgc_wpl
from sitl.missions.rectangle import TURN_MODES, Mission

FUZZ = budget(150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FRAME = StorageFrame((4.0, -6.0, 0.0), math.radians(70))


@pytest.fixture(scope="module")
def workdir():
    with tempfile.TemporaryDirectory(prefix="wpl-fuzz-") as d:
        yield Path(d)


@pytest.fixture(scope="module")
def good_plan(workdir) -> str:
    return write_qgc_wpl(workdir / "good.waypoints", Mission(p_traj=0.2), FRAME).read_text()


def read_both(path: Path) -> tuple[list | None, list | None]:
    """(rows, items) from the two readers, None where one refused the file (after checking how)."""
    try:
        rows = read_qgc_wpl(path)
    except ValueError as exc:  # UnicodeDecodeError included: the message must still name the file
        assert type(exc) is ValueError and str(path) in str(exc) and "\n" not in str(exc), repr(exc)
        rows = None
    try:
        items = load_plan(path)
    except GcsError as exc:
        assert str(path) in str(exc), repr(exc)
        items = None
    if rows is not None:
        assert all(len(r) == 12 and all(math.isfinite(v) for v in r) for r in rows)
    if items is not None:
        assert [m.seq for m in items] == list(range(len(items)))
    return rows, items


cell = st.one_of(
    st.floats().map(repr),
    st.integers(-(2**40), 2**40).map(str),
    st.sampled_from(["", "nan", "inf", "-inf", "1e400", "0x10", "1_000", "٣", "1.5", "-0", "65536", "256", "x"]),
    st.text(max_size=6),
)
wpl_line = st.one_of(
    st.lists(cell, min_size=10, max_size=13).map("\t".join),
    st.lists(cell, min_size=12, max_size=12).map(" ".join),
    st.just(""), st.just("# a comment"), st.text(max_size=40),
)
wpl_text = st.builds(lambda head, lines, nl: head + nl + nl.join(lines) + nl,
                     st.sampled_from(["QGC WPL 110", "QGC WPL 110 ", "QGC WPL 100", "QGC WPL PB 110", "", "qgc"]),
                     st.lists(wpl_line, max_size=8), st.sampled_from(["\n", "\r\n", "\r"]))


@FUZZ
@given(data=st.one_of(wpl_text.map(str.encode), st.binary(max_size=600), st.text(max_size=300).map(str.encode)))
def test_that_random_plan_files_load_whole_or_fail_with_one_clean_error(workdir, data):
    path = workdir / "fuzz.waypoints"
    path.write_bytes(data)
    read_both(path)


edits = st.lists(st.tuples(st.sampled_from(["delete", "insert", "replace", "swap-lines", "drop-line"]),
                           st.integers(0, 10**6), st.characters()), min_size=1, max_size=6)


def garble(text: str, ops: list[tuple[str, int, str]]) -> str:
    for op, pos, ch in ops:
        lines = text.split("\n")
        i, j = pos % (len(text) + 1), pos % max(1, len(lines))
        if op == "delete":
            text = text[:i] + text[i + 1:]
        elif op == "insert":
            text = text[:i] + ch + text[i:]
        elif op == "replace":
            text = text[:i] + ch + text[i + 1:]
        elif op == "swap-lines" and len(lines) > 1:
            lines[j], lines[j - 1] = lines[j - 1], lines[j]
            text = "\n".join(lines)
        elif op == "drop-line":
            text = "\n".join(lines[:j] + lines[j + 1:])
    return text


@FUZZ
@given(ops=edits)
def test_that_a_garbled_plan_loads_whole_or_fails_with_one_clean_error(workdir, good_plan, ops):
    path = workdir / "garbled.waypoints"
    text = garble(good_plan, ops)
    path.write_text(text, encoding="utf-8", errors="surrogatepass")
    rows, items = read_both(path)
    if text == good_plan:
        assert rows is not None and items is not None and len(rows) == len(items)


@budget(40, deadline=None)
@given(p_traj=st.floats(0.01, 0.49), speed=st.floats(0.05, 15), altitude=st.floats(0.5, 40),
       turn=st.sampled_from(TURN_MODES), dims=st.tuples(st.floats(5, 300), st.floats(5, 300), st.floats(3, 50)),
       origin=st.tuples(st.floats(-89, 89), st.floats(-180, 180), st.floats(-400, 8000)))
def test_that_any_valid_survey_plan_reads_back_to_the_same_rows_in_both_readers(workdir, p_traj, speed, altitude,
                                                                                turn, dims, origin):
    try:
        mission = Mission(storage=Storage(*dims), p_traj=p_traj, speed_m_s=speed, altitude_m=altitude, turn=turn)
    except ValueError:
        assume(False)
    path = write_qgc_wpl(workdir / "valid.waypoints", mission, FRAME, origin)
    rows, items = read_both(path)
    want = np.array(plan_rows(mission, FRAME, origin), dtype=float)
    got = np.array(rows)
    assert got[:, 0].tolist() == list(range(len(want))) and got[:, 1].tolist() == [1] + [0] * (len(want) - 1)
    assert np.array_equal(got[:, 2:4], want[:, :2]) and np.allclose(got[:, 4:11], want[:, 2:], rtol=0, atol=1e-6)
    assert len(items) == len(want)
    assert [(m.frame, m.command) for m in items] == [tuple(int(v) for v in r[:2]) for r in want]
    assert all(abs(m.x - r[6] * 1e7) <= 1 and abs(m.y - r[7] * 1e7) <= 1 for m, r in zip(items, want, strict=True))


@pytest.mark.parametrize(("line", "words"), [
    ("1\t0\t300\t16\t0\t0\t0\t0\t53.4\t-2.2\t12\t1", "item 1 cannot be sent"),  # frame is a uint8
    ("1\t0\t3\t16\t0\t0\t0\t0\t253.4\t-2.2\t12\t1", "item 1 cannot be sent"),  # lat x 1e7 beyond int32
    ("1\t0\t3\t16\t0\t0\t0\t0\tnan\t-2.2\t12\t1", "item 1 cannot be sent"),
    ("1\t0\t3\t16\t0\t0\t0\t0\t53.4\t-2.2\t1e39\t1", "item 1 cannot be sent"),  # z is a float32
    ("1\t0\t3\t16.5\t0\t0\t0\t0\t53.4\t-2.2\t12\t1", "malformed"),
    ("1\t0\t3\t16\t0\t0\t0", "malformed"),
])
def test_that_the_ground_station_refuses_a_plan_it_could_not_send_before_starting_the_upload(tmp_path, line, words):
    path = tmp_path / "bad.waypoints"
    path.write_text("QGC WPL 110\n0\t1\t0\t16\t0\t0\t0\t0\t53.4\t-2.2\t50\t1\n" + line + "\n")
    with pytest.raises(GcsError, match=words):
        load_plan(path)


def test_that_a_plan_that_is_not_a_regular_file_is_refused_at_once(tmp_path):
    fifo = tmp_path / "plan.waypoints"
    os.mkfifo(fifo)
    with pytest.raises(GcsError, match="not a regular file"):
        load_plan(fifo)  # a FIFO with no writer would block a plain read for ever
