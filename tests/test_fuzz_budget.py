"""The fuzz tests' budgets: CI draws what each test states, HYPOTHESIS_PROFILE=explore ten times as many."""

import re
from pathlib import Path

from tests.fuzz_budget import EXPLORE_FACTOR, budget

TESTS = Path(__file__).parent


def test_that_exploring_draws_ten_times_the_examples_ci_draws(monkeypatch):
    monkeypatch.delenv("HYPOTHESIS_PROFILE", raising=False)
    assert budget(30, deadline=None).max_examples == 30
    monkeypatch.setenv("HYPOTHESIS_PROFILE", "explore")
    assert budget(30, deadline=None).max_examples == 30 * EXPLORE_FACTOR == 300


def test_that_no_fuzz_test_sets_its_examples_past_the_rule():
    """A budget given to Hypothesis' settings directly outranks the explore profile's, and exploring would draw no
    more than CI (what every fuzz test did before the rule)."""
    raw = re.compile(r"settings\(\s*max_examples")
    offenders = [str(p.relative_to(TESTS)) for p in TESTS.rglob("*.py")
                 if p.name not in ("fuzz_budget.py", Path(__file__).name) and raw.search(p.read_text())]
    assert offenders == []
