"""The unseen-ground campaign's fixture piles and its command line."""

import math

import numpy as np
import pytest

from firmware_py.core.storage import Storage
from tools.unseen_campaign import REPOSE_SLOPE, fixture_piles, heightfield_pile, main


def test_that_the_corner_fixture_is_a_quarter_cone_of_its_stated_size():
    storage = Storage()
    shape = fixture_piles(storage)["corner"]
    pile = heightfield_pile(shape, storage, "corner")
    radius = shape.peak_m / REPOSE_SLOPE
    assert pile.volume_m3 == pytest.approx(math.pi * radius**2 * shape.peak_m / 3 / 4, rel=0.01)


def test_that_the_wall_end_fixture_leaves_both_corners_bare():
    storage = Storage()
    shape = fixture_piles(storage)["wall-end"]
    assert shape.height_m(np.array([0.0, 0.0]), np.array([0.0, storage.width_m])).max() == 0.0
    assert shape.height_m(np.array([0.0]), np.array([storage.width_m / 2]))[0] == pytest.approx(shape.peak_m)


@pytest.mark.parametrize("argv", [["--piles", "pyramid"], ["--positions", "0"], ["--positions", "21"]])
def test_that_bad_arguments_are_refused_with_one_line(argv, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("unseen_campaign:") and "\n" not in err
