"""Where the sample log goes: refused at once when it cannot be written, and how long the free space lasts."""

import os
from collections import namedtuple

import pytest

from firmware_py import log_room
from firmware_py.core.cli import UserError
from firmware_py.core.samplelog import HEAD_SIZE, SAMPLE_DTYPE
from firmware_py.log_room import LOW_ROOM_S, check_destination, describe_room, room_s, room_warning

Usage = namedtuple("Usage", "total used free")


def test_that_a_log_that_cannot_be_written_is_refused_in_one_line(tmp_path, monkeypatch):
    check_destination(tmp_path / "new.pslog", force=False)  # a new file in a writable directory: fine
    (tmp_path / "old.pslog").write_bytes(b"")
    with pytest.raises(UserError, match="already exists; choose another --out or pass --force"):
        check_destination(tmp_path / "old.pslog", force=False)
    check_destination(tmp_path / "old.pslog", force=True)
    with pytest.raises(UserError, match="it is a directory"):
        check_destination(tmp_path, force=True)
    with pytest.raises(UserError, match=r"directory .*nowhere does not exist"):
        check_destination(tmp_path / "nowhere" / "x.pslog", force=False)
    # Permission: the tests may run as root, whom mode bits do not stop, so the check is asked directly.
    monkeypatch.setattr(log_room.os, "access", lambda path, mode: not (mode & os.W_OK))
    with pytest.raises(UserError, match="no permission to create files in"):
        check_destination(tmp_path / "new.pslog", force=False)


def test_that_the_room_is_the_free_space_over_the_records_and_their_block_frames(tmp_path, monkeypatch):
    monkeypatch.setattr(log_room.shutil, "disk_usage", lambda path: Usage(10**9, 0, 29_513_000))
    per_s = (SAMPLE_DTYPE.itemsize + HEAD_SIZE / 500) * 500.0  # 59 bytes a record, a 13-byte frame per block
    assert room_s(tmp_path / "x.pslog", 500.0, 500) == pytest.approx(29_513_000 / per_s)
    assert room_s(tmp_path / "x.pslog", 500.0, 500) == pytest.approx(1000.0, rel=1e-3)  # 1000 s at 500 Hz

    def gone(path):
        raise OSError("no such file system")
    monkeypatch.setattr(log_room.shutil, "disk_usage", gone)
    assert room_s(tmp_path / "x.pslog", 500.0, 500) is None  # not known: no warning either
    assert room_warning(None, None, 500.0) is None


def test_that_too_little_room_is_warned_against_the_flight_or_half_an_hour():
    assert room_warning(2 * LOW_ROOM_S, None, 500.0) is None
    low = room_warning(LOW_ROOM_S / 3, None, 500.0)
    assert low is not None and "room for 10 min of samples at 500 Hz, less than half an hour (30 min)" in low
    assert room_warning(LOW_ROOM_S / 3, 300.0, 500.0) is None  # a 5-minute --duration fits in 10 minutes
    assert "less than the --duration (1 h 40 min)" in room_warning(LOW_ROOM_S / 3, 6000.0, 500.0)
    assert describe_room(45.0) == "45 s" and describe_room(7500.0) == "2 h 05 min"
