"""The surface file's versions: version 2 carries the fitted cells' mask, version 1 still reads (mask unknown); and
the one check of its metadata numbers that both readers (the ground's and the planner's) use."""

import json

import numpy as np
import pytest

from firmware_py.core.surface_file import FORMAT, FORMAT_VERSION, meta_number, read_surface_file


def _write(path, version, fitted=None, shape=(4, 3)):
    arrays = {"heights_m": np.zeros(shape), "meta": np.array(json.dumps({"format": FORMAT,
                                                                          "format_version": version}))}
    if fitted is not None:
        arrays["fitted"] = fitted
    np.savez(path, **arrays)
    return path


def edit_meta(path, key, value):
    """The surface file at path with its metadata field key set to value (removed for None), as damage or a hand
    edit would leave it (both readers' tests damage files so)."""
    with np.load(path) as z:
        arrays = {k: z[k] for k in z.files}
    meta = json.loads(str(arrays["meta"]))
    if value is None:
        del meta[key]
    else:
        meta[key] = value
    np.savez(path, **{**arrays, "meta": np.array(json.dumps(meta))})
    return path


BUILDING_OR_CELL_CASES = [
    ("length_m", float("nan"), r"length_m must be a finite number >= 0\.001, got nan"),
    ("width_m", None, r"width_m must be a finite number >= 0\.001, got None"),  # missing
    ("height_m", "10", r"height_m must be a finite number >= 0\.001, got '10'"),
    ("height_m", True, r"height_m must be a finite number >= 0\.001, got True"),
    ("length_m", 0.0, r"length_m must be a finite number >= 0\.001, got 0\.0"),
    ("cell_m", 0.005, r"cell_m must be a finite number >= 0\.01, got 0\.005"),
    ("cell_m", 10 ** 400, r"cell_m must be a finite number >= 0\.01, got 1000"),  # OverflowError before
]
"""A building or a cell that is no usable number, and the line both readers refuse it with (the same bounds)."""


def test_that_version_2_carries_the_fitted_mask_and_version_1_reads_without_it(tmp_path):
    mask = np.array([[True, False, True]] * 4)
    raw = read_surface_file(_write(tmp_path / "v2.npz", 2, mask))
    assert FORMAT_VERSION == 2 and np.array_equal(raw.fitted, mask)
    old = read_surface_file(_write(tmp_path / "v1.npz", 1))
    assert old.fitted is None and old.heights_m.shape == (4, 3)


@pytest.mark.parametrize("version, fitted, message", [
    (3, None, "version 3 is not one of the supported 1, 2"),
    (True, None, "version True is not one of the supported"),
    (2, None, "lacks its fitted cells' mask"),
    (1, np.ones((4, 3), dtype=bool), "holds a fitted mask"),
    (2, np.ones((4, 3)), "fitted mask is float64"),
    (2, np.ones((3, 4), dtype=bool), "not bool (4, 3)"),
])
def test_that_a_file_whose_version_and_arrays_disagree_is_refused(tmp_path, version, fitted, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        read_surface_file(_write(tmp_path / "s.npz", version, fitted))


@pytest.mark.parametrize("meta, got", [
    ({}, "got None"),  # missing
    ({"cell_m": None}, "got None"),
    ({"cell_m": "0.5"}, "got '0.5'"),
    ({"cell_m": True}, "got True"),  # a JSON boolean is not 1 m
    ({"cell_m": [0.5]}, r"got \[0\.5\]"),
    ({"cell_m": float("nan")}, "got nan"),
    ({"cell_m": float("inf")}, "got inf"),
    ({"cell_m": 10 ** 400}, "got 1000"),  # a JSON integer beyond a float: no OverflowError
    ({"cell_m": 0.005}, "got 0.005"),  # under the minimum
    ({"cell_m": 2.5}, "got 2.5"),  # over the maximum
])
def test_that_a_metadata_number_that_is_not_a_finite_number_within_its_bounds_is_one_line(meta, got):
    with pytest.raises(ValueError, match=r"^s\.npz: surface file field cell_m must be a finite number within 0\.01 "
                                         rf"to 2, {got}") as e:
        meta_number(meta, "cell_m", "s.npz", minimum=0.01, maximum=2.0)
    assert "\n" not in str(e.value) and len(str(e.value)) <= 300


def test_that_a_metadata_number_within_its_bounds_is_a_float_and_the_bounds_are_inclusive():
    assert meta_number({"n": 3}, "n", "s.npz") == 3.0 and isinstance(meta_number({"n": 3}, "n", "s.npz"), float)
    assert meta_number({"n": 0.01}, "n", "s.npz", minimum=0.01, maximum=2.0) == 0.01
    assert meta_number({"n": 2}, "n", "s.npz", minimum=0.01, maximum=2.0) == 2.0
    assert meta_number({"n": -1.5}, "n", "s.npz", minimum=-2.0) == -1.5


def test_that_a_metadata_numbers_bound_is_worded_as_it_is_checked():
    with pytest.raises(ValueError, match=r"field n must be a finite number >= 0, got -1$"):
        meta_number({"n": -1}, "n", "s.npz")  # at least 0 by default, no maximum
