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


@pytest.mark.parametrize("bad", [True, False, "60", None, [60]])
def test_that_storage_dimensions_given_as_json_booleans_or_strings_are_refused(bad) -> None:
    with pytest.raises(ValueError, match=r"length_m must be a number|length must be"):
        Storage.from_dict({"length_m": bad, "width_m": 40, "height_m": 15})
    with pytest.raises(ValueError):
        Storage(True, 1.0, 1.0)  # type: ignore[arg-type]
