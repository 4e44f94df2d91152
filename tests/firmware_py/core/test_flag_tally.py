"""Flag tallies tell no-returns (nothing in range) from faults, counted from the samples' own flags."""

import numpy as np

from firmware_py.core.flag_tally import FlagTally, describe_flag_counts
from firmware_py.core.samplelog import SampleFlags


def test_that_samples_flagged_only_no_return_are_no_returns_not_faults():
    t = FlagTally()
    t.add(np.full(2302, int(SampleFlags.NO_RETURN), dtype=np.uint8))
    assert (t.samples, t.usable, t.no_return_only, t.faulty) == (2302, 0, 2302, 0)
    assert t.describe() == "usable 0, no return 2,302, faulty 0"


def test_that_any_fault_flag_makes_a_sample_faulty_and_each_flag_is_counted():
    t = FlagTally()
    flags = [0, 0, int(SampleFlags.SENSOR_ERROR), int(SampleFlags.NO_RETURN | SampleFlags.STALE_POSE),
             int(SampleFlags.NO_POSE), int(SampleFlags.NO_RETURN)]
    for f in flags:  # one 0-d sample at a time, as the payload loop hands them
        t.add(np.array(f, dtype=np.uint8))
    assert (t.samples, t.usable, t.no_return_only, t.faulty, t.flagged) == (6, 2, 1, 3, 4)
    assert t.per_flag[SampleFlags.NO_RETURN] == 2
    assert t.describe() == "usable 2, no return 1, faulty 3 (sensor error 1, stale pose 1, no pose 1)"


def test_that_counts_are_described_by_name_and_nothing_says_none():
    assert describe_flag_counts({SampleFlags.SENSOR_ERROR: 168, SampleFlags.NO_RETURN: 0}) == "sensor error 168"
    assert describe_flag_counts({SampleFlags.STALE_POSE: 12_345}) == "stale pose 12,345"  # grouped, as the page prints
    assert describe_flag_counts({}) == "none"
