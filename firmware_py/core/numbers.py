"""What counts as a number where a user, a file or a peer gives one.

JSON and TOML hand Python bools where a number was meant (`true` is an int to Python, yet not 1 m), and NaN or an
infinity where a writer failed: every contract that reads a number asks the same question, so it is asked here once.
"""

from __future__ import annotations

import math
from typing import Any


def is_number(v: Any) -> bool:
    """An int or a float, not a bool (NaN and the infinities are numbers here; `is_finite_number` refuses them)."""
    return isinstance(v, int | float) and not isinstance(v, bool)


def is_finite_number(v: Any) -> bool:
    """An int or a float, not a bool, neither NaN nor infinite."""
    return is_number(v) and math.isfinite(v)
