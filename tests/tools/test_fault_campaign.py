"""The fault campaign's bookkeeping: loop rate, the targets' checks, bad inputs (the flights themselves
are covered fault by fault in tests/sitl/faults/test_injector.py)."""

import math

import numpy as np
import pytest

from tools.fault_campaign import RECORDS_PER_BLOCK, checks, loop_rate_hz, main, scenarios


def row(name="none", **kw):
    r = {"name": name, "wrong": 0, "ve_pct": 1.0, "lost": 0, "in_flight": 0, "ends_early": False,
         "rate_min_hz": 500.0}
    r.update(kw)
    return r


def test_that_the_loop_rate_is_counted_per_whole_second_and_a_stall_shows():
    t = np.arange(0, 10, 1 / 500)
    med, low = loop_rate_hz(t)
    assert med == 500 and low == 500
    stalled = t[(t < 4.0) | (t >= 4.5)]  # half a second without samples
    assert loop_rate_hz(stalled)[1] == 250
    assert all(math.isnan(v) for v in loop_rate_hz(t[:100]))  # too short to say


def test_that_every_target_fails_when_its_condition_fails():
    good = [row(), row("loss-10", ve_pct=1.3), row("loss-30", ve_pct=1.9),
            row("power-cut", lost=RECORDS_PER_BLOCK + 40, in_flight=40, ends_early=True)]
    assert all("**yes**" in line for line in checks(good, 500.0))
    bad_cases = [
        (0, {"wrong": 1}, "wrongly tagged"),
        (1, {"ve_pct": 1.6}, "loss-10"),
        (2, {"ve_pct": 2.1}, "loss-30"),
        (3, {"lost": RECORDS_PER_BLOCK + 41}, "data lost"),
        (1, {"lost": 1}, "data lost"),  # a run that does not end early loses nothing
        (1, {"rate_min_hz": 480.0}, "rate"),
    ]
    for i, change, words in bad_cases:
        rows = [dict(r) for r in good]
        rows[i].update(change)
        failed = [line for line in checks(rows, 500.0) if "**NO**" in line]
        assert len(failed) == 1 and words in failed[0], (change, failed)


def test_that_the_random_kill_time_is_seeded_and_inside_the_survey():
    a = {s.name: s for s in scenarios(1)}["kill-random"].spec.power_cut_at_s
    b = {s.name: s for s in scenarios(1)}["kill-random"].spec.power_cut_at_s
    c = {s.name: s for s in scenarios(2)}["kill-random"].spec.power_cut_at_s
    assert a == b != c and 5.0 <= a <= 115.0


@pytest.mark.parametrize("argv, words", [
    (["--only", "nope"], "no scenario nope"),
    (["--p-traj", "80"], "--p-traj"),
    (["--p-traj", "nan"], "finite"),
    (["--stockpile", "7"], "stockpile"),
    (["--write", "/no/such/dir/r.md"], "directory must exist"),
])
def test_that_bad_inputs_give_one_line_and_exit_2(argv, words, capsys):
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and words in err
