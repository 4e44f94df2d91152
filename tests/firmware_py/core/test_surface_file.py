"""The surface file's versions: version 2 carries the fitted cells' mask, version 1 still reads (mask unknown)."""

import json

import numpy as np
import pytest

from firmware_py.core.surface_file import FORMAT, FORMAT_VERSION, read_surface_file


def _write(path, version, fitted=None, shape=(4, 3)):
    arrays = {"heights_m": np.zeros(shape), "meta": np.array(json.dumps({"format": FORMAT,
                                                                          "format_version": version}))}
    if fitted is not None:
        arrays["fitted"] = fitted
    np.savez(path, **arrays)
    return path


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
