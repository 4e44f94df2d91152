"""Re-estimating the servo's real motion from the sweeps themselves, when its model is wrong.

A hobby servo has no feedback: each sample's angle is the firmware's model of the shaft
(`firmware_py.drivers.servo`). When the real servo trails that model, the rising and the falling
sweeps put the same floor at different heights (`ground.consistency`). Two faults cover what a
servo does wrong on the paper's semi-triangular sweep:

- a dead time d (it answers each pulse d late): the real angle is the model's angle d earlier,
  exactly, since a delayed pulse train gives a delayed trajectory;
- a slower top speed than calibrated: on a triangle wave the shaft then slews at its own limit
  all the time and turns back early, so its path is again a triangle, of the same centre and
  period but a smaller swing, and later.

When the log header says how the servo was driven (its calibration and when the sweep started,
`servo_calibration` and `servo_drive`, written by the payload and the SITL), the firmware's own
servo model is run again on the same pulses, answering them d late and slewing at g times the
calibrated rate (`Resimulated`): exact for both faults, turn-backs included. Otherwise the real
angle is approximated from the logged one as c + g (gamma_model(t - d) - c), c the centre of the
logged sweep (`ShiftScale`): exact for a dead time; for a slow servo right along the sweep but
not where it turns back (the real shaft turns in a sharp corner where the command is rounded).

Either way (d, g) is chosen to make the two sweep directions agree best: a coarse grid over both,
then alternating fine line searches (the objective is a median over histogram cells: piecewise
flat, which gradient and simplex methods stall on). The fit is accepted only if it brings the
disagreement under the trust threshold; it is reported either way, never applied silently.
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field, replace

import numpy as np

from firmware_py.core.header import ServoDrive, waveform_from_dict
from firmware_py.core.servo_model import CommandStates, ServoCalibration, angles_at, sweep_states
from firmware_py.core.waveform import Waveform
from ground.plausibility import MAX_GAP_S
from ground.remembered import Remembered

DELAY_RANGE_S = (-0.05, 0.15)
"""Dead times searched: a faster-than-modelled servo leads (d < 0); 150 ms is 3 pulse periods at
the 50 Hz PWM frame and a fifth of the paper's 0.67 Hz sweep period."""
GAIN_RANGE = (0.3, 1.2)
"""Speed (or swing) ratios searched: a servo at 30 % of its calibrated speed to one 20 % faster."""
COARSE_DELAY_STEP_S = 0.025
COARSE_GAIN_STEP = 0.1
FINE_STEPS = 5  # each side of the current optimum, at a fifth (then a twenty-fifth) of the coarse step
LAST_BUT_ONE_STEP_S = COARSE_DELAY_STEP_S / FINE_STEPS
"""The search's delay step before its last (5 ms): its delay is within it of the sweeps' best, whatever their noise."""
MAX_FINE_ROUNDS = 8
REMEMBERED_STATES_BYTES = 64 * 2**20
"""What a drive (`Resimulated`) keeps of the servo's states stepped at each speed a search tried (a 187 s flight's
take 0.2 MB a speed): the search comes back to a speed for every delay it tries there."""


@dataclass(frozen=True)
class ServoTiming:
    """What the sweeps say about the real servo: it answers delay_s late, and its speed (re-simulated)
    or its swing (shift-scale) is gain times the model's."""

    delay_s: float
    gain: float
    model: str  # Resimulated.name or ShiftScale.name
    disagreement_before_m: float
    disagreement_after_m: float
    evaluations: int
    building_shift_m: float | None = None
    """Set when the delay is the one the floor and walls showed beside the pose's drift (`ground.plane_stretches.
    beside_a_servo_delay`), not the search's: the RMS it moved their points by. Then gain is 1 (a dead time)."""
    refined_s: float | None = None
    """Set when the floor and walls refined the search's delay (the report's `_refined_by_building`): what they added
    to it (s); delay_s includes it."""


def sweep_center_rad(servo_rad: np.ndarray) -> float:
    """The middle of the logged sweep (the waveform's centre: the paper's sweep is symmetric about it)."""
    a = np.asarray(servo_rad, dtype=float)
    a = a[np.isfinite(a)]
    return float((a.min() + a.max()) / 2) if len(a) else 0.0


def retimed(samples: np.ndarray, delay_s: float, gain: float, center_rad: float) -> np.ndarray:
    """A copy of the samples with the servo angle (and sweep direction) of a servo that trails the
    logged model by delay_s and swings gain times as far about center_rad."""
    out = samples.copy()
    t = samples["t_s"].astype(float)
    model = samples["servo_rad"].astype(float)
    shifted = np.interp(t - delay_s, t, model)  # t is the log's time order; ends clamp
    out["servo_rad"] = center_rad + gain * (shifted - center_rad)
    if "sweep_dir" in samples.dtype.names and len(samples) > 1:
        # The direction of the model, shifted: the real shaft turns back d later than the model did.
        d_idx = np.interp(t - delay_s, t, samples["sweep_dir"].astype(float))
        out["sweep_dir"] = np.where(d_idx >= 0, 1, -1).astype(samples["sweep_dir"].dtype)
    return out


@dataclass(frozen=True)
class ShiftScale:
    """The real shaft from the logged angles alone: c + g (gamma_model(t - d) - c)."""

    center_rad: float
    name = "shift-scale"

    def apply(self, samples: np.ndarray, delay_s: float, gain: float) -> np.ndarray:
        return retimed(samples, delay_s, gain, self.center_rad)


@dataclass
class Resimulated:
    """The firmware's servo model run again on the pulses it sent, the servo answering them delay_s
    late and slewing at gain times its calibrated rate."""

    waveform: Waveform
    cal: ServoCalibration
    t0_s: float
    frame_s: float
    name = "servo model"
    _nominal: dict = field(default_factory=dict, repr=False, compare=False)
    _nominal_lock: threading.Lock = field(default_factory=threading.Lock, repr=False, compare=False)
    _states: Remembered[CommandStates] = field(
        default_factory=lambda: Remembered(REMEMBERED_STATES_BYTES, lambda st: 3 * st.cmd_t_s.nbytes),
        repr=False, compare=False)

    @classmethod
    def from_header(cls, header: dict) -> Resimulated | None:
        """From the header's servo, servo_calibration and servo_drive; None if any is missing or bad."""
        try:
            wf = waveform_from_dict(header["servo"])
            drive = ServoDrive.from_dict(header["servo_drive"])
            cal = ServoCalibration(**{k: float(v) for k, v in header["servo_calibration"].items()})
        except (KeyError, TypeError, ValueError, AttributeError):
            return None
        return cls(wf, cal, drive.t0_s, drive.frame_s)

    def drives(self, t_s: np.ndarray) -> bool:
        """Whether this drive can be the one behind samples at t_s: it started before the last of them and no
        longer before the first than a flight's longest pause (`ground.plausibility.MAX_GAP_S`). A re-simulation
        steps every PWM frame from the drive's start, so a start a clock fault moved by days would step for
        hours."""
        t = np.asarray(t_s, dtype=float)
        t = t[np.isfinite(t)]
        return len(t) > 0 and float(t.min()) - MAX_GAP_S <= self.t0_s <= float(t.max())

    def angles(self, t_s: np.ndarray, delay_s: float = 0.0, gain: float = 1.0) -> np.ndarray:
        """`modelled_sweep` of this drive at times t_s, the servo delay_s late at gain times its speed; the pulses
        stepped once a speed (`_sweep_states`), so a search's delays at one speed cost only their queries."""
        cal = replace(self.cal, slew_rad_s=self.cal.slew_rad_s * gain)
        t = np.asarray(t_s, dtype=float) - self.t0_s - delay_s
        return angles_at(t, self._sweep_states(cal, t.max() if len(t) else 0.0), cal)

    def _sweep_states(self, cal: ServoCalibration, until_s: float) -> CommandStates:
        """`sweep_states` of this drive at this calibration to at least until_s: remembered, stepped to the span of
        the delays searched beyond it, so every delay a search tries at this speed is answered from one stepping
        (the same angles to the bit: `sweep_states`)."""
        got = self._states.get(cal, lambda st: len(st.cmd_t_s) > 0 and st.cmd_t_s[-1] >= until_s)
        if got is not None:
            return got
        states = sweep_states(self.waveform, cal, until_s + DELAY_RANGE_S[1] - DELAY_RANGE_S[0], self.frame_s)
        self._states.put(cal, states)
        return states

    def apply(self, samples: np.ndarray, delay_s: float, gain: float) -> np.ndarray:
        """The logged angles plus what the fault changes (re-simulated faulty minus re-simulated
        nominal): the re-simulation's own small differences from the payload's model (its pulses
        go out on the loop's ticks, not on an exact 20 ms grid: up to ~0.5 deg) cancel."""
        out = samples.copy()
        t = samples["t_s"]
        key = (len(t), float(t[0]), float(t[-1])) if len(t) else (0,)
        with self._nominal_lock:  # a search tries its candidates on several threads
            if key not in self._nominal:  # the same for every candidate (d, g) of a search
                self._nominal.clear()
                self._nominal[key] = self.angles(t)
            nominal = self._nominal[key]
        angle = samples["servo_rad"].astype(float) + self.angles(t, delay_s, gain) - nominal
        out["servo_rad"] = angle
        if len(samples) > 1:
            turning = np.sign(np.gradient(angle))
            out["sweep_dir"] = np.where(turning == 0, samples["sweep_dir"], turning).astype(samples["sweep_dir"].dtype)
        return out


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    return np.round(np.arange(lo, hi + step / 2, step), 6)


def estimate_servo_timing(samples: np.ndarray, disagreement: Callable[[np.ndarray], float | None],
                          before_m: float, motion: ShiftScale | Resimulated | None = None,
                          floor_m: float = 0.0, threads: int = 1) -> ServoTiming | None:
    """(d, g) that minimise disagreement(motion.apply(samples, d, g)) (module docstring; default
    motion: ShiftScale about the logged sweep's centre); None if it cannot be measured (too few
    cells where both sweep directions land).

    Two models compete: a dead time alone (g = 1), and a dead time with a speed (or swing) factor.
    The second always fits at least as well, and a smaller swing makes the sweeps agree more for
    the wrong reason (the far, grazing points, where angle errors matter most, move in), so the
    dead time alone is kept unless the factor improves the agreement by more than floor_m: the
    statistic's own noise (the disagreement of two random halves of the same points).

    threads: how many candidates are tried at once (each is independent: the same (d, g) on any count). The
    disagreement must then be safe to call from several threads.
    """
    motion = motion if motion is not None else ShiftScale(sweep_center_rad(samples["servo_rad"]))
    with ThreadPoolExecutor(threads) if threads > 1 else nullcontext() as pool:
        return _search(samples, disagreement, before_m, motion, floor_m, pool)


def _search(samples: np.ndarray, disagreement: Callable[[np.ndarray], float | None], before_m: float,
            motion: ShiftScale | Resimulated, floor_m: float, pool: ThreadPoolExecutor | None) -> ServoTiming | None:
    """`estimate_servo_timing`'s search, each grid's new candidates tried on the pool's threads (None: in turn)."""
    evals = 0
    cache: dict[tuple[float, float], float] = {}

    def tried(key: tuple[float, float]) -> float:
        v = disagreement(motion.apply(samples, key[0], key[1]))
        return np.inf if v is None else v

    def key_of(d: float, g: float) -> tuple[float, float]:  # a candidate's name: its delay and gain to a micro-unit
        return round(float(d), 6), round(float(g), 6)

    def cost(d: float, g: float) -> float:
        nonlocal evals
        key = key_of(d, g)
        if key not in cache:
            evals += 1
            cache[key] = tried(key)
        return cache[key]

    def best_of(ds, gs) -> tuple[float, float]:
        nonlocal evals
        keys = [key_of(d, g) for d in ds for g in gs]
        new = [k for k in dict.fromkeys(keys) if k not in cache]
        if pool is not None and len(new) > 1:
            cache.update(zip(new, pool.map(tried, new), strict=True))
            evals += len(new)
        return min(keys, key=lambda dg: cost(*dg))

    fine = np.arange(-FINE_STEPS, FINE_STEPS + 1)

    def refine(d: float, g: float, with_gain: bool) -> tuple[float, float]:
        for level in (FINE_STEPS, FINE_STEPS**2):
            for _ in range(MAX_FINE_ROUNDS):  # coupled (a later servo also looks slower): alternate
                d1, g1 = best_of(d + COARSE_DELAY_STEP_S / level * fine, [g])
                if with_gain:
                    d1, g1 = best_of([d1], g1 + COARSE_GAIN_STEP / level * fine)
                if (d1, g1) == (d, g):
                    break
                d, g = d1, g1
        return d, g

    delays = _grid(*DELAY_RANGE_S, COARSE_DELAY_STEP_S)
    d_only = refine(*best_of(delays, [1.0]), with_gain=False)
    # The two trade against each other along a narrow valley: the coarse search covers both at once.
    both = refine(*best_of(delays, _grid(*GAIN_RANGE, COARSE_GAIN_STEP)), with_gain=True)
    d, g = d_only if cost(*d_only) <= cost(*both) + floor_m else both
    after = cost(d, g)
    if not np.isfinite(after):
        return None
    return ServoTiming(d, g, motion.name, before_m, float(after), evals)
