"""Fixtures shared by the mission tests."""

import dataclasses

import pytest


@pytest.fixture
def one_speed(monkeypatch):
    """The real coverage planner at one speed (2 m/s) for the command-line tests; the targets it was asked for,
    in order. The search over four speeds is the planner's own tests' (tests/sitl/missions/test_coverage.py);
    on the command line it made these tests the suite's slowest."""
    import sitl.missions.coverage as coverage
    real, seen = coverage.plan_coverage, []

    def plan(storage, target, **kw):
        seen.append(target)
        return real(storage, dataclasses.replace(target, speeds_m_s=(2.0,)), **kw)

    monkeypatch.setattr(coverage, "plan_coverage", plan)
    return seen
