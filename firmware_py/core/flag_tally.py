"""What flagged samples are, in the words the operator needs: no return (nothing in range: normal over
open floor or beyond the sensor's reach) versus faulty (a sensor error, a pose that cannot be
vouched for, a servo angle in doubt).

The payload's status line and the ground's `listen` summary both count from the samples' own flags,
so what they print is what the sample log holds (a status line that counted the LiDAR driver's
transfer failures said "sensor errors 0" beside 168 SENSOR_ERROR samples: readings taken while the
part reloaded after an automatic reset are logged SENSOR_ERROR but are no failed transfer).
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from firmware_py.core.samplelog import SampleFlags

FLAG_WORDS: dict[SampleFlags, str] = {
    SampleFlags.NO_RETURN: "no return",
    SampleFlags.SENSOR_ERROR: "sensor error",
    SampleFlags.STALE_POSE: "stale pose",
    SampleFlags.NO_POSE: "no pose",
    SampleFlags.SERVO_UNCERTAIN: "servo uncertain",
}
"""Each flag as the operator reads it, in the order lines list them."""
FAULT_FLAGS = SampleFlags.SENSOR_ERROR | SampleFlags.STALE_POSE | SampleFlags.NO_POSE | SampleFlags.SERVO_UNCERTAIN
"""Flags that say something went wrong (NO_RETURN alone says only that nothing was in range)."""


class FlagTally:
    """Running counts of samples: usable, no return only, faulty, and per flag (a sample may carry several)."""

    def __init__(self) -> None:
        self.samples = 0
        self.no_return_only = 0
        self.faulty = 0
        self.per_flag: dict[SampleFlags, int] = dict.fromkeys(FLAG_WORDS, 0)

    @property
    def usable(self) -> int:
        return self.samples - self.no_return_only - self.faulty

    @property
    def flagged(self) -> int:
        return self.no_return_only + self.faulty

    def add(self, flags: np.ndarray) -> None:
        """Count the samples whose `flags` field is given (any integer array, or a 0-d one)."""
        f = np.asarray(flags).reshape(-1).astype(np.int64, copy=False)
        if not f.size:
            return
        self.samples += int(f.size)
        faulty = (f & int(FAULT_FLAGS)) != 0
        self.faulty += int(np.count_nonzero(faulty))
        self.no_return_only += int(np.count_nonzero(~faulty & ((f & int(SampleFlags.NO_RETURN)) != 0)))
        for flag in FLAG_WORDS:
            self.per_flag[flag] += int(np.count_nonzero(f & int(flag)))

    def describe(self) -> str:
        """E.g. "usable 0, no return 2,302, faulty 0" or "... faulty 168 (sensor error 168)": thousands grouped, as
        the live page and the reports print every other count beside it."""
        return f"usable {self.usable:,}, no return {self.no_return_only:,}, faulty {self.faulty:,}" + (
            f" ({describe_flag_counts({f: n for f, n in self.per_flag.items() if f & FAULT_FLAGS})})"
            if self.faulty else "")


def describe_flag_counts(counts: Mapping[SampleFlags, int]) -> str:
    """Non-zero counts by flag in the operator's words ("sensor error 1,168, stale pose 3"), or "none"."""
    parts = [f"{word} {counts.get(flag, 0):,}" for flag, word in FLAG_WORDS.items() if counts.get(flag, 0)]
    return ", ".join(parts) if parts else "none"
