"""Re-estimating the servo's real motion from the sweeps themselves, when its model is wrong.

A hobby servo has no feedback: each sample's angle is the firmware's model of the shaft
(`firmware_py.drivers.servo`). When the real servo trails that model, the rising and the falling
sweeps put the same floor at different heights (`ground.consistency`). Two faults cover what a
servo does wrong on the paper's semi-triangular sweep:

- a dead time d (it answers each pulse d late): the real angle is the model's angle d earlier,
  exactly, since a delayed pulse train gives a delayed trajectory;
- a slower top speed than calibrated: on a triangle wave the shaft then slews at its own limit
  all the time and turns back early, so its path is again a triangle, of the same centre and
  period but a smaller swing, and later: g * (model(t - d) - c) + c with g < 1.

So the real angle is modelled as gamma(t) = c + g * (gamma_model(t - d) - c), c the centre of the
logged sweep, and (d, g) is chosen to make the two sweep directions agree best: a coarse grid,
then alternating fine line searches (the objective is a median over histogram cells: piecewise
flat, which gradient and simplex methods stall on). The fit is accepted only if it brings the
disagreement under the trust threshold; it is reported either way, never applied silently.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

DELAY_RANGE_S = (-0.05, 0.15)
"""Dead times searched: a faster-than-modelled servo leads (d < 0); 150 ms is 3 pulse periods at
the 50 Hz PWM frame and a fifth of the paper's 0.67 Hz sweep period."""
GAIN_RANGE = (0.3, 1.2)
"""Swing ratios searched: a servo at 30 % of its calibrated speed to one 20 % faster."""
COARSE_DELAY_STEP_S = 0.01
COARSE_GAIN_STEP = 0.05
FINE_STEPS = 5  # each side of the coarse optimum, at a fifth of the coarse step
MAX_FINE_ROUNDS = 8


@dataclass(frozen=True)
class ServoTiming:
    """What the sweeps say about the real servo: it trails the model by delay_s and swings gain times as far."""

    delay_s: float
    gain: float
    center_rad: float
    disagreement_before_m: float
    disagreement_after_m: float
    evaluations: int


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
    angle = center_rad + gain * (shifted - center_rad)
    out["servo_rad"] = angle
    if "sweep_dir" in samples.dtype.names and len(samples) > 1:
        # The direction of the model, shifted: the real shaft turns back d later than the model did.
        d_idx = np.interp(t - delay_s, t, samples["sweep_dir"].astype(float))
        out["sweep_dir"] = np.where(d_idx >= 0, 1, -1).astype(samples["sweep_dir"].dtype)
    return out


def _grid(lo: float, hi: float, step: float) -> np.ndarray:
    return np.round(np.arange(lo, hi + step / 2, step), 6)


def estimate_servo_timing(samples: np.ndarray, disagreement: Callable[[np.ndarray], float | None],
                          before_m: float) -> ServoTiming | None:
    """(d, g) that minimise disagreement(retimed samples) (module docstring); None if it cannot be
    measured (too few cells where both sweep directions land)."""
    center = sweep_center_rad(samples["servo_rad"])
    evals = 0
    cache: dict[tuple[float, float], float] = {}

    def cost(d: float, g: float) -> float:
        nonlocal evals
        key = (round(d, 6), round(g, 6))
        if key not in cache:
            evals += 1
            v = disagreement(retimed(samples, d, g, center))
            cache[key] = np.inf if v is None else v
        return cache[key]

    def best_of(ds, gs) -> tuple[float, float]:
        return min(((d, g) for d in ds for g in gs), key=lambda dg: cost(*dg))

    d, g = best_of(_grid(*DELAY_RANGE_S, COARSE_DELAY_STEP_S), [1.0])
    d, g = best_of([d], _grid(*GAIN_RANGE, COARSE_GAIN_STEP))
    d, g = best_of(_grid(*DELAY_RANGE_S, COARSE_DELAY_STEP_S), [g])  # the delay again, at that swing
    fine = np.arange(-FINE_STEPS, FINE_STEPS + 1)
    for _ in range(MAX_FINE_ROUNDS):  # the two are coupled (a later shaft also looks smaller): alternate
        d1, g1 = best_of(d + COARSE_DELAY_STEP_S / FINE_STEPS * fine, [g])
        d1, g1 = best_of([d1], g1 + COARSE_GAIN_STEP / FINE_STEPS * fine)
        if (round(d1, 6), round(g1, 6)) == (round(d, 6), round(g, 6)):
            break
        d, g = d1, g1
    after = cost(d, g)
    if not np.isfinite(after):
        return None
    return ServoTiming(float(d), float(g), center, before_m, float(after), evals)
