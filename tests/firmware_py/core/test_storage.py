import pytest

from firmware_py.core.storage import Storage


def test_that_storage_parses_lxwxh():
    assert Storage.parse("60x40x15") == Storage(60, 40, 15)
    assert Storage.parse(" 30.5 X 20 x 8 ") == Storage(30.5, 20, 8)


@pytest.mark.parametrize("text", ["60x40", "axbxc", "60x40x15x3", "", "nanx40x15", "60x-40x15", "60x40x0"])
def test_that_bad_storage_strings_are_refused_with_a_message(text):
    with pytest.raises(ValueError, match="storage"):
        Storage.parse(text)


def test_that_storage_round_trips_through_a_dict():
    s = Storage(12.0, 8.0, 6.0)
    assert Storage.from_dict(s.to_dict()) == s
