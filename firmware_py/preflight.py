"""The payload's preflight check (`pilescan-payload --preflight`): the parts working together, judged before take-off.

`--check` reads the configuration without opening anything. A payload whose configuration is right can still fly a
survey that cannot be used: the servo on its own BEC left unpowered (the beam points one way for the whole flight),
the signal wire on the wrong pin, the rangefinder's I2C wiring marginal, the autopilot not streaming the pose at the
rate asked, an indoor EKF without an origin, the card full. Each of these shows only in the log, after the flight.
ArduPilot answers the same problem for the autopilot with its pre-arm checks; this is the payload's.

`PayloadApp.preflight` opens the hardware as a flight does, runs the same loop for a few sweep periods into memory
(no log is written) and hands what it saw to the pure functions here, each of which gives one `Check`: a name, a
`Verdict` and one line saying what was seen and, when it is wrong, what to look at.

The servo has no position feedback, so whether it moves is read from the ranges: swept from straight down to
level on either side, the beam meets the floor below at a fraction of a metre and the room's far parts at metres,
so the ranges' medians over the sweep's sectors differ by far more than the sensor's noise. A servo that does not
move leaves the beam on one spot, and those medians then agree within the noise (`sweep_check`).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleFlags
from firmware_py.pose import PoseSample

SECTORS = 12
"""The sweep's angle range split into this many sectors for the sweep check (15 deg each over +-90 deg)."""
MIN_SECTOR_RANGES = 5
"""Ranges a sector needs for its median to count."""
MIN_SECTORS = 3
"""Sectors with ranges needed to judge whether the beam moved."""
STILL_SIGMAS = 10.0
"""A sweep whose sector medians all lie within this many of the sensor's range sigmas of each other left the beam
where it was: a sector's median of 5 or more noisy ranges is off by about a sigma at most, so 10 leaves no doubt
either way, while a beam swept from the floor below to level moves its range by metres."""
PREFLIGHT_SWEEPS = 3.0
"""Sweep periods the preflight samples: each sector is then seen in both directions, more than once."""
MIN_PREFLIGHT_S = 5.0
"""Shortest preflight sampling: the pose stream's rate is measured over a second, the link's over a few."""
MAX_ERROR_SHARE = 0.01
"""Failed readings (bus errors, bad frames) above this share of the readings are worth a look at the wiring: a
sound part on sound wiring fails none."""
MAX_NO_RETURN_SHARE = 0.5
"""No echo on more than half the readings on the ground: a covered lens, or a beam that meets nothing in range."""
MIN_RATE_SHARE = 0.9
"""A loop or a stream below this share of its rate is worth saying: the sample density the survey was planned for
is not reached."""
MIN_POSED_SHARE = 0.5
"""Fewer samples than this share with a usable pose: the survey's points could not be placed."""
MIN_POSE_RATE_SHARE = 0.8
"""A pose stream below this share of the rate asked: the autopilot's stream rates or the link's bandwidth."""


class Verdict(enum.Enum):
    """What a check found: fine, worth a look before the flight, or a flight that would be wasted."""

    OK = "ok"
    WARN = "warning"
    FAIL = "FAIL"


@dataclass(frozen=True)
class Check:
    """One preflight check: its name, what it found, and one line saying what was seen."""

    name: str
    verdict: Verdict
    detail: str


@dataclass(frozen=True)
class PreflightResult:
    """Every check of one preflight, in the order they are printed."""

    checks: tuple[Check, ...]
    duration_s: float
    readings: int

    @property
    def passed(self) -> bool:
        """No check failed (warnings allowed)."""
        return all(c.verdict is not Verdict.FAIL for c in self.checks)

    def named(self, verdict: Verdict) -> list[str]:
        return [c.name for c in self.checks if c.verdict is verdict]

    def lines(self) -> list[str]:
        """The checklist as printed: a verdict column, a name column, the detail."""
        width = max((len(c.name) for c in self.checks), default=0)
        out = [f"preflight: {self.duration_s:.1f} s, {self.readings:,} readings"]
        out += [f"  {c.verdict.value:<8} {c.name:<{width}}  {c.detail}" for c in self.checks]
        failed, warned = self.named(Verdict.FAIL), self.named(Verdict.WARN)
        if failed:
            out.append(f"preflight FAILED: {', '.join(failed)}")
        else:
            out.append("preflight passed" + (f" with {len(warned)} warning{'s' * (len(warned) > 1)}" if warned else ""))
        return out

    def statustext(self) -> str:
        """What the ground station is shown (the STATUSTEXT prefix added by the caller): short, as a pre-arm message."""
        failed = self.named(Verdict.FAIL)
        return f"preflight FAIL: {', '.join(failed)}" if failed else "preflight ok"


def _range_sigma_m(range_m: float, sigma_m: float, sigma_rel: float) -> float:
    """The sensor's stated range sigma at a range (the header's model: the larger of the two terms)."""
    return max(sigma_m, sigma_rel * range_m)


def sweep_check(servo_rad: np.ndarray, range_m: np.ndarray, amplitude_rad: float, sigma_m: float,
                sigma_rel: float, pwm_url: str) -> Check:
    """Whether the beam moved with the servo's commanded sweep (module docstring).

    servo_rad: each valid range's modelled servo angle; range_m: the ranges (no flagged reading).
    """
    name = "servo sweep"
    servo_rad, range_m = np.asarray(servo_rad, float), np.asarray(range_m, float)
    edges = np.linspace(-amplitude_rad, amplitude_rad, SECTORS + 1)
    sector = np.clip(np.searchsorted(edges, servo_rad, side="right") - 1, 0, SECTORS - 1)
    commanded = np.unique(sector).size if servo_rad.size else 0
    medians = [float(np.median(range_m[sector == k])) for k in range(SECTORS)
               if np.count_nonzero(sector == k) >= MIN_SECTOR_RANGES]
    swept = f"+-{math.degrees(amplitude_rad):.0f} deg"
    if len(medians) < MIN_SECTORS:
        return Check(name, Verdict.WARN,
                     f"ranges in only {len(medians)} of the sweep's {SECTORS} sectors: cannot tell whether the beam "
                     "moves (point it at the floor and walls, not the sky)")
    low, high = min(medians), max(medians)
    still = STILL_SIGMAS * _range_sigma_m(float(np.median(medians)), sigma_m, sigma_rel)
    if high - low <= still:
        return Check(name, Verdict.FAIL,
                     f"the range stayed at {np.median(medians):.2f} m (within {100 * (high - low):.1f} cm over "
                     f"{len(medians)} sectors) while the servo was driven over {swept}: is the servo powered, its "
                     f"signal wire on the output {pwm_url} drives, and the beam's view clear?")
    return Check(name, Verdict.OK,
                 f"the range follows the sweep: sector medians {low:.2f}-{high:.2f} m over {swept} "
                 f"({len(medians)} of {commanded} sectors with ranges)")


def rangefinder_check(readings: int, no_return: int, errors: int, range_m: np.ndarray, duration_s: float,
                      rate_hz: float, what: str) -> Check:
    """Readings, echoes and failures of the rangefinder over the preflight; what: its name and port, for the line."""
    name = "rangefinder"
    if readings == 0:
        return Check(name, Verdict.FAIL, f"no reading from the {what}")
    valid = readings - no_return - errors
    rate = readings / duration_s if duration_s > 0 else 0.0
    counts = (f"{readings:,} readings at {rate:.0f} Hz: {100 * valid / readings:.0f} % ranged, "
              f"{100 * no_return / readings:.0f} % no echo, {errors:,} failed")
    if valid == 0:
        return Check(name, Verdict.FAIL, f"no range at all from the {what} ({counts}): its wiring, power, "
                                         "address, and a clear lens")
    spread = (f"; {np.min(range_m):.2f}-{np.median(range_m):.2f}-{np.max(range_m):.2f} m (min-median-max)"
              if np.size(range_m) else "")
    if errors > MAX_ERROR_SHARE * readings:
        verdict = Verdict.FAIL if errors > valid else Verdict.WARN
        return Check(name, verdict, f"{counts}{spread}: failed readings point to the wiring (pull-ups, a loose "
                                    "connector) or the part's power")
    if no_return > MAX_NO_RETURN_SHARE * readings:
        return Check(name, Verdict.WARN, f"{counts}{spread}: a covered lens, or nothing in range?")
    if rate < MIN_RATE_SHARE * rate_hz:
        return Check(name, Verdict.WARN, f"{counts}{spread}: slower than the {rate_hz:g} Hz configured")
    return Check(name, Verdict.OK, counts + spread)


def loop_check(ticks: int, overruns: int, rate_hz: float) -> Check:
    """Whether the companion computer kept the loop's tick grid (a loop paced by its own clock)."""
    slots = ticks + overruns
    if slots == 0:
        return Check("loop", Verdict.FAIL, "the loop did not run")
    share = overruns / slots
    line = f"{ticks:,} ticks at {rate_hz:g} Hz, {overruns:,} missed ({100 * share:.1f} %)"
    if share > 1.0 - MIN_RATE_SHARE:
        return Check("loop", Verdict.WARN, f"{line}: the computer is too busy for this rate (other programs? a "
                                           "lower --rate?)")
    return Check("loop", Verdict.OK, line)


def autopilot_check(heard: bool, armed: bool | None, target_system: int, mavlink_url: str) -> Check:
    """Whether the autopilot answers on the link."""
    if not heard:
        return Check("autopilot", Verdict.FAIL,
                     f"nothing from system {target_system} on {mavlink_url}: is the autopilot on, the link's port and "
                     "baud rate right, and MAVLink 2 enabled on its serial port (SERIALn_PROTOCOL = 2)?")
    state = "armed" if armed else "disarmed" if armed is False else "no HEARTBEAT yet"
    return Check("autopilot", Verdict.OK, f"system {target_system} answers on {mavlink_url} ({state})")


POSE_STREAMS = ("ATTITUDE", "LOCAL_POSITION_NED")


def pose_check(posed_share: float, pose_status: str, rates_hz: Mapping[str, float], stream_hz: float,
               rtt_ms: float | None, origin_sent: bool) -> Check:
    """Whether the samples can be posed: the share of the preflight's samples that got a usable pose (time sync
    converged, both pose streams fresh), and the streams' rates against the rate asked.

    posed_share: that share, in [0, 1] (without samples, 1 or 0 as the pose is usable at the end); pose_status: the
    tracker's line saying what is missing.
    """
    rates = ", ".join(f"{k} {rates_hz.get(k, 0.0):.0f} Hz" for k in POSE_STREAMS)
    posed = f"{100 * posed_share:.0f} % of the samples posed"
    if posed_share < MIN_POSED_SHARE:
        hint = ""
        if rates_hz.get("LOCAL_POSITION_NED", 0.0) == 0.0:
            hint = ("; no LOCAL_POSITION_NED: an indoor EKF publishes it once it has an origin" +
                    (" (the origin was sent: is the EKF's position source set?)" if origin_sent else
                     " (--origin or --send-origin sends one)"))
        return Check("pose", Verdict.FAIL, f"{posed}: {pose_status} ({rates}){hint}")
    sync = f"; time sync round trip {rtt_ms:.1f} ms" if rtt_ms is not None else ""
    if posed_share < 1.0 - MAX_ERROR_SHARE:
        return Check("pose", Verdict.WARN, f"{posed} ({rates}{sync}): the pose came late or not at all for the "
                                           f"others: {pose_status}")
    slow = [k for k in POSE_STREAMS if rates_hz.get(k, 0.0) < MIN_POSE_RATE_SHARE * stream_hz]
    if slow:
        return Check("pose", Verdict.WARN, f"{posed}; {rates}, asked {stream_hz:g} Hz{sync}: the autopilot's stream "
                                           "rates or the link's bandwidth (baud rate, other streams)")
    return Check("pose", Verdict.OK, f"{posed}; {rates}{sync}")


def ekf_source_check(answered: bool, description: str | None, height_from_rangefinder: bool,
                     autopilot_heard: bool) -> Check:
    """What the autopilot's pose comes from (its EKF3 sources), and a downward rangefinder height worth changing."""
    if not autopilot_heard:
        return Check("EKF sources", Verdict.WARN, "not read: the autopilot did not answer")
    if not answered or description is None:
        return Check("EKF sources", Verdict.WARN, "the autopilot did not answer EK3_SRC1_*: the log will not say "
                                                  "what the pose came from")
    if height_from_rangefinder:
        return Check("EKF sources", Verdict.WARN,
                     f"{description}: over a stockpile a rangefinder height places every point low by a share of "
                     "the pile's height; a barometer height is surer (EK3_SRC1_POSZ = 1)")
    return Check("EKF sources", Verdict.OK, description)


def origin_check(disagreement: str | None) -> Check | None:
    """The autopilot's EKF origin against the one sent (None when there is nothing to compare)."""
    return None if disagreement is None else Check("EKF origin", Verdict.FAIL, disagreement)


def log_check(problem: str | None, room_line: str | None, low_room: str | None) -> Check:
    """Whether the flight's sample log can be written, and the room its card holds."""
    if problem is not None:
        return Check("sample log", Verdict.FAIL, problem)
    if low_room is not None:
        return Check("sample log", Verdict.WARN, low_room)
    return Check("sample log", Verdict.OK, room_line or "writable")


def opening_check(name: str, error: str) -> Check:
    """A part that could not be opened (the error names it and its URL)."""
    return Check(name, Verdict.FAIL, error)


RANGE_FAILURE = SampleFlags.NO_RETURN | SampleFlags.SENSOR_ERROR
"""The flags that leave a sample without a range (the pose flags do not matter to the sensor's checks)."""


class MemorySink:
    """Where the preflight's loop puts its records: memory, not a log (a preflight writes no file)."""

    def __init__(self) -> None:
        self.chunks: list[np.ndarray] = []

    def append(self, records: np.ndarray) -> None:
        self.chunks.append(np.atleast_1d(records).copy())

    def flush(self) -> None:
        pass

    def samples(self) -> np.ndarray:
        """The records so far, as one array (empty when none)."""
        return np.concatenate(self.chunks) if self.chunks else np.zeros(0, dtype=SAMPLE_DTYPE)


class NoPose:
    """A pose source for a preflight whose autopilot link could not be opened: the rangefinder and the servo are
    still checked, every sample without a pose."""

    def pump(self) -> None:
        pass

    def pose_at(self, t_ns: int) -> PoseSample:
        nan = math.nan
        return PoseSample(t_ns, (nan, nan, nan), nan, nan, nan, math.inf, True, True)
