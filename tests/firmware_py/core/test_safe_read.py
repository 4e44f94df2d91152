"""Bounded, type-checked reads: no hang on a FIFO, no endless read of a device, no RecursionError."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from firmware_py.core.safe_read import (
    MAX_JSON_DEPTH,
    InputError,
    json_number,
    json_object,
    load_json,
    parse_json,
    read_bounded,
)


def test_that_a_regular_file_within_the_limit_is_read_whole(tmp_path: Path) -> None:
    p = tmp_path / "f"
    p.write_bytes(b"x" * 100)
    assert read_bounded(p, 100) == b"x" * 100


def test_that_a_file_larger_than_the_limit_is_refused_by_its_size_before_reading(tmp_path: Path) -> None:
    p = tmp_path / "huge"
    with open(p, "wb") as f:
        f.truncate(3 * 1024**3)  # sparse: 3 GiB claimed, nothing written
    with pytest.raises(InputError, match="3,221,225,472 bytes, more than the 1,000 byte limit"):
        read_bounded(p, 1000)


@pytest.mark.skipif(not os.path.exists("/dev/zero"), reason="needs /dev/zero")
def test_that_dev_zero_is_refused_as_a_device_not_read_until_memory_runs_out() -> None:
    with pytest.raises(InputError, match="character device, not a regular file"):
        read_bounded("/dev/zero", 10**12)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_that_a_fifo_with_no_writer_is_refused_at_once_instead_of_hanging(tmp_path: Path) -> None:
    fifo = tmp_path / "pipe"
    os.mkfifo(fifo)
    with pytest.raises(InputError, match="FIFO"):
        read_bounded(fifo, 1000)  # a blocking open would never return: no writer exists


def test_that_a_directory_is_refused(tmp_path: Path) -> None:
    with pytest.raises((InputError, IsADirectoryError, PermissionError)):
        read_bounded(tmp_path, 1000)


def test_that_deeply_nested_json_gives_one_line_not_a_recursion_error(tmp_path: Path) -> None:
    p = tmp_path / "deep.json"
    p.write_text("[" * 1_000_000 + "]" * 1_000_000)
    with pytest.raises(InputError, match=f"deeper than {MAX_JSON_DEPTH} levels") as info:
        load_json(p, "truth file")
    assert "\n" not in str(info.value)


def test_that_nesting_within_the_limit_and_brackets_inside_strings_are_accepted() -> None:
    text = "[" * MAX_JSON_DEPTH + json.dumps("[[[[{{{{\\\"") + "]" * MAX_JSON_DEPTH
    value = parse_json(text, "x")
    for _ in range(MAX_JSON_DEPTH):
        value = value[0]
    assert value == '[[[[{{{{\\"'


@pytest.mark.parametrize("raw, why", [(b"\xff\xfe{}", "not UTF-8"), (b"{", "not valid JSON"),
                                      (b'{"v": NaN}', "not valid JSON"), (b'{"v": Infinity}', "not valid JSON")])
def test_that_bad_json_is_refused_in_one_line_naming_the_file(raw: bytes, why: str) -> None:
    with pytest.raises(InputError, match=why):
        parse_json(raw, "truth file t.json")


def test_that_a_utf8_bom_is_tolerated() -> None:
    assert parse_json("\ufeff{\"a\": 1}".encode(), "x") == {"a": 1}


@pytest.mark.parametrize("value", [True, False, None, "5", [5], float("nan"), float("inf")])
def test_that_a_json_boolean_or_non_number_is_not_a_number(value) -> None:
    with pytest.raises(InputError, match="must be a finite number"):
        json_number(value, "storage.length_m")


def test_that_numbers_pass_and_positivity_is_checked() -> None:
    assert json_number(3, "x") == 3.0 and isinstance(json_number(3, "x"), float)
    with pytest.raises(InputError, match="must be a positive number, got 0"):
        json_number(0, "x", positive=True)
    with pytest.raises(InputError, match="JSON object"):
        json_object([1], "x")
