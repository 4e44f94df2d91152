"""The two-lobe test pile is what its tool makes, and a valid pile for the TFMini's bay."""

import pytest

from firmware_py.core.storage import Storage
from sitl.world.stockpile import resolve, volume_under_mesh
from tools.make_two_lobe_pile import DEFAULT_OUT, STORAGE, two_lobe_mesh


def test_that_the_stored_pile_is_the_tools_pile_and_loads_as_a_height_field_in_its_bay():
    pile = resolve(str(DEFAULT_OUT), Storage(30, 20, 10))
    assert STORAGE == Storage(30, 20, 10)
    assert pile.volume_m3 == pytest.approx(volume_under_mesh(two_lobe_mesh()), rel=1e-6)
    assert pile.max_height_m == pytest.approx(6.0) and pile.volume_m3 == pytest.approx(1335.86, abs=0.01)
