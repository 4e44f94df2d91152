"""The fuzz tests' example budgets, one rule for all of them.

Each fuzz test states how many examples CI draws (the same ones on every run: the "ci" profile in tests/conftest.py is
derandomized); under HYPOTHESIS_PROFILE=explore it draws ten times as many, at random. A budget a test sets itself
outranks the profile's, so before this rule the explore profile drew no more examples than CI on every fuzz test
that states its budget, which all of them do.
"""

import os

from hypothesis import settings

EXPLORE_FACTOR = 10
"""How many times CI's examples the explore profile draws."""


def profile_name() -> str:
    """The Hypothesis profile this run loads (tests/conftest.py): HYPOTHESIS_PROFILE, "ci" without it."""
    return os.environ.get("HYPOTHESIS_PROFILE", "ci")


def exploring() -> bool:
    """HYPOTHESIS_PROFILE=explore: look for new failing inputs rather than repeat CI's."""
    return profile_name() == "explore"


def budget(max_examples: int, **kwargs) -> settings:
    """Hypothesis settings drawing max_examples for CI, ten times as many when exploring (kwargs as `settings`)."""
    return settings(max_examples=max_examples * (EXPLORE_FACTOR if exploring() else 1), **kwargs)
