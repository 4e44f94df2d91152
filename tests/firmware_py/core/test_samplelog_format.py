"""The reader checks the format a log states: name, version and record layout."""

from __future__ import annotations

import io
import json
from pathlib import Path

import pytest

from firmware_py.core.safe_read import InputError
from firmware_py.core.samplelog import (
    FORMAT_NAME,
    FORMAT_VERSION,
    SAMPLE_DTYPE,
    SampleLogWriter,
    UnsupportedLogFormat,
    encode_block,
    new_records,
    read_samplelog,
)


def log_with(**keys) -> bytes:
    header = {"format": FORMAT_NAME, "format_version": FORMAT_VERSION,
              "record_dtype": [list(p) for p in SAMPLE_DTYPE.descr], **keys}
    return encode_block(b"H", json.dumps(header).encode()) + encode_block(b"S", new_records(3).tobytes())


def test_that_a_log_the_writer_wrote_is_of_a_supported_format(tmp_path: Path) -> None:
    with SampleLogWriter(tmp_path / "x.pslog", {"a": 1}, fsync=False) as w:
        w.append(new_records(2))
    log = read_samplelog(tmp_path / "x.pslog")
    assert log.format_problem is None
    log.require_supported_format("x.pslog")


def test_that_a_version_99_log_is_refused_naming_what_it_found_and_what_is_supported() -> None:
    log = read_samplelog(log_with(format_version=99))
    assert len(log.samples) == 3  # recovered, but ...
    with pytest.raises(UnsupportedLogFormat) as info:
        log.require_supported_format("run/samples.pslog")
    msg = str(info.value)
    assert "run/samples.pslog" in msg and "version 99" in msg and "supports version 1" in msg and "\n" not in msg


@pytest.mark.parametrize("keys, found", [
    ({"format": "lidar-dump"}, '"lidar-dump"'),
    ({"format_version": "1"}, 'version "1"'),
    ({"format_version": True}, "version true"),
    ({"format_version": 0}, "version 0"),
    ({"record_dtype": [["t_s", "<f8"], ["range_m", "<f8"]]}, "layout [[\"t_s\", \"<f8\"]"),
    ({"record_dtype": "whatever"}, 'layout "whatever"'),
])
def test_that_another_format_version_or_record_layout_is_refused(keys: dict, found: str) -> None:
    problem = read_samplelog(log_with(**keys)).format_problem
    assert problem is not None and found in problem


def test_that_a_header_without_format_keys_is_read_as_the_current_layout() -> None:
    data = encode_block(b"H", b'{"n": 1}') + encode_block(b"S", new_records(1).tobytes())
    assert read_samplelog(data).format_problem is None


def test_that_a_log_path_larger_than_the_limit_is_refused_before_reading(tmp_path: Path) -> None:
    p = tmp_path / "big.pslog"
    with open(p, "wb") as f:
        f.truncate(5 * 1024**3)  # sparse
    with pytest.raises(InputError, match="more than the"):
        read_samplelog(p)
    with pytest.raises(InputError, match="more than the 10 byte limit"):
        read_samplelog(p, max_bytes=10)


def test_that_a_file_object_is_read_bounded_too() -> None:
    with pytest.raises(InputError, match="more than the 100 byte limit"):
        read_samplelog(io.BytesIO(b"\0" * 1000), max_bytes=100)


def test_that_dev_zero_is_refused_as_a_sample_log() -> None:
    with pytest.raises(InputError, match="character device"):
        read_samplelog("/dev/zero")
