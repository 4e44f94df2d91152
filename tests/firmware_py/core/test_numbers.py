"""What counts as a number: one answer for every contract that reads numbers from a user, a file or a peer."""

import math

import numpy as np
import pytest

from firmware_py.core.numbers import is_finite_number, is_number


@pytest.mark.parametrize("v", [0, -3, 2.5, np.float64(1.0), 1e308])
def test_that_ints_and_floats_are_finite_numbers(v):
    assert is_number(v) and is_finite_number(v)


@pytest.mark.parametrize("v", [True, False, "1", None, [1.0], 1 + 0j])
def test_that_a_bool_a_string_or_a_list_is_no_number(v):
    assert not is_number(v) and not is_finite_number(v)


@pytest.mark.parametrize("v", [math.nan, math.inf, -math.inf])
def test_that_nan_and_the_infinities_are_numbers_but_not_finite(v):
    assert is_number(v) and not is_finite_number(v)
