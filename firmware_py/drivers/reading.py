"""What every rangefinder driver hands the payload loop: a range, or why there is none.

One reading type for all drivers (the LIDAR-Lite on I2C, the TFMini family on a UART), so the loop,
the sample-log flags and the health counters never ask which sensor is fitted.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import IntEnum


class ReadStatus(IntEnum):
    """What a reading is: a range, or why there is none."""

    OK = 0
    NO_RETURN = 1  # the part measured and saw no valid echo (LIDAR-Lite: 1 cm or 0; TFMini: weak/saturated)
    TIMEOUT = 2  # the part did not answer before the deadline (busy never cleared; no frame arrived)
    BUS_ERROR = 3  # a transfer failed, or the bytes read cannot be a distance
    RESETTING = 4  # the part is reloading after an automatic reset: not triggered, no bus traffic


@dataclass(frozen=True)
class Reading:
    """One measurement.

    Attributes:
        range_m: the range in metres, None unless status is OK.
        status: why there is or is not a range.
        t_ns: when the part measured, on the driver's clock (each driver's docstring says how it knows).
        polls: how many times the driver looked before the measurement was there.
    """

    range_m: float | None
    status: ReadStatus
    t_ns: int
    polls: int

    def __post_init__(self) -> None:
        if self.status is ReadStatus.OK or self.status == ReadStatus.OK:  # identity first: 500 a second
            if self.range_m is None or not math.isfinite(self.range_m) or self.range_m < 0.0:
                raise ValueError(f"an OK reading needs a finite range >= 0 m, got {self.range_m!r}")
        elif self.range_m is not None:
            raise ValueError(f"a {self.status.name} reading has no range, got {self.range_m!r}")
        if self.polls < 0:
            raise ValueError(f"polls must be >= 0, got {self.polls}")

    @property
    def ok(self) -> bool:
        return self.status == ReadStatus.OK
