"""Isolated range spikes: samples that stand out from both time-neighbours while the neighbours agree.

A garbage I2C read whose random distance bytes happen to be plausible, or a sensor glitch, puts one
sample (rarely two) metres off the surface that the samples before and after it see. In the cloud
that is a lone point in the air or in the ground, and the Clough-Tocher fit through it runs away
(one 1 m spike at 13 m emptied 136 cells in the 2 % garbage campaign). The test works on the
time-ordered usable samples before they become points. Two usable samples are time-neighbours when
at most MAX_GAP_PERIODS sample periods apart: one flagged sample between them (often the garbage
read next door) does not break the chain, longer gaps do.

- A single sample m between neighbours a and b is a spike when it differs from both by more than
  T, in the same sense (r_m is a local extremum), and a and b agree within A.
- A pair m1, m2 between a and b is a spike when each differs from both by more than T, in the same
  sense, and a and b agree within T. The garbage model draws every read independently, so pairs
  are rare (~4e-6 per sample at 2 %: none in five campaign seeds); a glitch value read twice (a
  garbage status byte makes the driver read the distance registers early, which still hold the
  previous result) could give one too. It costs one more vectorised pass and is exactly as safe as
  the single test (below).

A step that persists (an edge, an occlusion) is kept: on one side of it the sample agrees with its
neighbour. What is dropped besides faults is a real surface narrower than two beam steps seen
against a background (a cable, a thin post: <= 2 delta r, 29 cm at 12 m), which costs nothing for
a stockpile's volume.

Thresholds, from the log header (r: the mean range of a and b, the surface's range, since the
spike's own range is meaningless; span: the time between the two samples compared):

    T(r) = k sqrt(2) sigma_r(r) + q + r (cos(psi/2) / cos(psi/2 + delta) - 1)
    A(r) = k sqrt(2) sigma_r(r) + q + r (cos(a_max) / cos(a_max + delta_ab) - 1)
    delta = omega * span + k sqrt(2) sigma_a,   omega = omega_servo + omega_body

- Noise: sigma_r(r) = max(range_sigma_m, range_sigma_rel * r) from ``sensor``; the difference of two
  samples has sqrt(2) sigma_r. Pure Gaussian noise makes a sample differ from both neighbours by
  more than k sqrt(2) sigma_r in the same sense with probability 2 Phi2(-k, -k; rho = 1/2):
  k = N_SIGMA = 4 gives 1e-6 per sample, i.e. < 0.1 false positives in a 64k-sample survey even if
  the sensor really were as noisy as the header's accuracy figure (1 % of range for the LIDAR-Lite;
  its sample-to-sample noise is lower) and each false positive costs one real sample, no bias,
  while a missed spike can wreck a surface (measured: none in 2.2M samples with noise at the full
  header sigma, the geometric term adds margin). q = ``resolution_m`` covers quantisation.
- Beam step: the beam turns at most omega: the servo's peak rate (from the eq. (1) waveform in
  ``servo``: 5 rad/s in Table 1) plus BODY_RATE_ALLOWANCE_RAD_S for the vehicle's own rotation;
  delta = 0.012 rad between consecutive samples at ``sensor.rate_hz`` = 500 Hz.
- Pointing noise: sigma_a is each sample's own beam-angle error the header's ``sensor_noise`` record states
  (servo and attitude, `stated_angle_sigma_rad`; 0 without one). Two samples' true beams then differ by the
  nominal step plus an error of sqrt(2) sigma_a; on a slanted surface that moves the range far more than the
  range noise does. And the extremum argument below no longer holds: with each beam jittered, the true
  angles of three consecutive samples can come out of order, so the middle one stands out from both
  neighbours on a single plane. T is then A's bound (a plane seen at up to a_max), over the step with its
  pointing errors. Without this the test took Appendix A's 1 deg per-sample servo noise for spikes on
  slopes (about 880 of 60,000 samples of pile 1 at P_traj 20 %, none a fault, mean signed Ve -0.66 % over 8
  servo positions against -0.33 % without despiking; with the pointing term but T's 45 deg geometry still
  ~270, -0.42 %). Such a header's T is wide (a gross fault only), which is what its pointing noise allows.
- Geometry of T: a sample can stand out from both neighbours in the same sense only at a range
  extremum, where the surface turns through the beam direction. The chords a-m and m-b then have
  incidences of opposite sign that add up to the angle between the chords, which is at most the
  surface's turn psi between a and b; so one of them is within psi/2 of normal incidence, and on a
  plane at incidence i the range changes by r (cos i / cos(i + delta) - 1) per step. With
  psi <= MAX_TURN_DEG = 90 deg (a right-angled corner: wall feet, box corners; a stockpile at an
  angle of repose <= 45 deg turns less at its crest and its foot), i.e. a stated maximum incidence
  of 45 deg on the flatter side of the extremum, that is 1.2 % of r (0.15 m at 12 m). It covers
  kinks, where the smooth-surface second difference r (1 + 2 tan^2 i) delta^2 (0.11 m at 12 m and
  80 deg) does not hold. So no continuous surface turning by <= 90 deg between two beam hits can
  trigger either test, whatever the noise within k sigma.
- Geometry of A: a and b could lie on one continuous surface seen at up to MAX_INCIDENCE_DEG = 80 deg
  (16 % of r over two steps). Agreement is what keeps edge configurations (a sample between two
  different surfaces) out; A only widens it to steep surfaces, where two samples apart already
  differ by more than T. The pair test keeps T: over three steps A would let a spike next to a real
  edge drag two real samples out with it.

T is 0.84 m at 12 m, 1.04 m at 15 m and 2.8 m at the LIDAR-Lite's 40 m (``max_range_m``); garbage is
spread over 0-60 m, so about 3 % of the plausible garbage stays within T of the surface. Those cannot be
told from noise of the header's size; a 0.7 m one at 15 m still moved the volume by 0.14 pp in one
of five campaign seeds (docs/design-notes.md). Without the servo waveform or the sample rate in the
header the beam's step is unknown and nothing is removed (`SpikeThreshold.from_header` gives None).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from firmware_py.core.sensor_noise import stated_angle_sigma_rad
from firmware_py.core.waveform import peak_rate

N_SIGMA = 4.0
"""Noise allowance of T and A, in sigmas of the difference of two samples (1e-6 false positives per sample)."""
MAX_TURN_DEG = 90.0
"""A continuous surface turning by at most this much between two beam hits never triggers the test."""
MAX_INCIDENCE_DEG = 80.0
"""Neighbours that could lie on one surface seen at up to this incidence agree (single test)."""
BODY_RATE_ALLOWANCE_RAD_S = 1.0
"""The vehicle's own rotation, added to the servo's rate (57 deg/s; the survey's yaw limit is 30 deg/s)."""
MAX_GAP_PERIODS = 2.5
"""Usable samples at most this many sample periods apart are time-neighbours (one missing sample between)."""


def _growth(incidence_rad: float, step_rad: np.ndarray) -> np.ndarray:
    """Relative range change of a plane seen at incidence_rad when the beam turns by step_rad away from
    its normal; inf when that reaches grazing (then no bound exists)."""
    end = incidence_rad + np.asarray(step_rad, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        g = math.cos(incidence_rad) / np.cos(end) - 1.0
    return np.where(end < math.pi / 2, g, np.inf)


@dataclass(frozen=True)
class SpikeThreshold:
    """T(r) and A(r) of the module docstring.

    Attributes:
        sample_period_s: 1 / f_s.
        beam_rate_rad_s: omega, the fastest the beam turns (servo peak rate + body allowance).
        range_sigma_m, range_sigma_rel, resolution_m: the sensor's error model (header ``sensor``).
        angle_sigma_rad: each sample's own pointing error (the header's ``sensor_noise`` servo and attitude
            sigmas, `stated_angle_sigma_rad`): two samples' beams then differ by up to k sqrt(2) of it more than
            the servo's nominal step.
        n_sigma: k.
        max_turn_rad: psi_max (T).
        max_incidence_rad: a_max (A).
    """

    sample_period_s: float
    beam_rate_rad_s: float
    range_sigma_m: float = 0.0
    range_sigma_rel: float = 0.0
    resolution_m: float = 0.0
    angle_sigma_rad: float = 0.0
    n_sigma: float = N_SIGMA
    max_turn_rad: float = math.radians(MAX_TURN_DEG)
    max_incidence_rad: float = math.radians(MAX_INCIDENCE_DEG)

    def __post_init__(self) -> None:
        for name in ("sample_period_s", "beam_rate_rad_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"spike threshold {name} must be finite and > 0, got {v!r}")
        for name in ("range_sigma_m", "range_sigma_rel", "resolution_m", "angle_sigma_rad", "n_sigma"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"spike threshold {name} must be finite and >= 0, got {v!r}")
        if not 0.0 <= self.max_turn_rad < math.pi:
            raise ValueError(f"spike threshold max turn must be in [0, 180) deg, got {math.degrees(self.max_turn_rad)}")
        if not 0.0 <= self.max_incidence_rad < math.pi / 2:
            raise ValueError("spike threshold max incidence must be in [0, 90) deg, got "
                             f"{math.degrees(self.max_incidence_rad)}")

    def step_rad(self, span_s: np.ndarray | float | None = None) -> np.ndarray:
        """delta: the most the beam turns in span_s (default one sample period), its two ends' pointing errors
        included."""
        nominal = self.beam_rate_rad_s * np.asarray(self.sample_period_s if span_s is None else span_s, dtype=float)
        return nominal + self.n_sigma * math.sqrt(2.0) * self.angle_sigma_rad

    def _noise(self, r: np.ndarray) -> np.ndarray:
        sigma = np.maximum(self.range_sigma_m, self.range_sigma_rel * r)
        return self.n_sigma * math.sqrt(2.0) * sigma + self.resolution_m

    def __call__(self, range_m: np.ndarray | float, span_s: np.ndarray | float | None = None) -> np.ndarray:
        """T: the most a sample at range r can stand out from a neighbour span_s away (default one sample
        period) on a continuous surface at a range extremum."""
        r = np.abs(np.asarray(range_m, dtype=float))
        incidence = self.max_turn_rad / 2 if self.angle_sigma_rad == 0 else self.max_incidence_rad
        return self._noise(r) + r * _growth(incidence, self.step_rad(span_s))

    def agree(self, range_m: np.ndarray | float, span_s: np.ndarray | float | None = None) -> np.ndarray:
        """A: the most two samples span_s apart at range r differ on one surface seen at up to a_max."""
        r = np.abs(np.asarray(range_m, dtype=float))
        return self._noise(r) + r * _growth(self.max_incidence_rad, self.step_rad(span_s))

    @classmethod
    def from_header(cls, header: dict, *, n_sigma: float = N_SIGMA, max_turn_deg: float = MAX_TURN_DEG,
                    max_incidence_deg: float = MAX_INCIDENCE_DEG,
                    body_rate_rad_s: float = BODY_RATE_ALLOWANCE_RAD_S) -> SpikeThreshold | None:
        """The thresholds the log header implies; None when it lacks a usable sample rate or servo waveform:
        then the beam's step, and so T, is unknown."""
        sensor = header.get("sensor") or {}
        servo = header.get("servo") or {}
        if not isinstance(sensor, dict) or not isinstance(servo, dict):
            return None
        if not all(_finite(d.get(k)) for d, k in ((sensor, "rate_hz"), (servo, "shape_c"), (servo, "frequency_hz"),
                                                     (servo, "amplitude_rad"))):
            return None  # absent, or not a number (a JSON true is not 1 Hz)
        try:
            rate_hz = float(sensor["rate_hz"])
            omega = peak_rate(float(servo["shape_c"]), float(servo["frequency_hz"]), float(servo["amplitude_rad"]))
            noise = [float(sensor.get(k) or 0.0) for k in ("range_sigma_m", "range_sigma_rel", "resolution_m")]
            if not (math.isfinite(omega) and omega > 0):
                return None
            return cls(1.0 / rate_hz, omega + body_rate_rad_s, *noise, stated_angle_sigma_rad(header), n_sigma=n_sigma,
                       max_turn_rad=math.radians(max_turn_deg), max_incidence_rad=math.radians(max_incidence_deg))
        except (KeyError, TypeError, ValueError, ZeroDivisionError, OverflowError):
            return None


def why_no_threshold(header: dict) -> str | None:
    """Why `SpikeThreshold.from_header` gives None for this header (one line naming what is missing or
    bad), or None when it gives a threshold: a report must not say despiking ran when it could not."""
    if SpikeThreshold.from_header(header) is not None:
        return None
    sensor = header.get("sensor")
    servo = header.get("servo")
    bad = [f"sensor.{k}" for k in ("rate_hz",) if not (isinstance(sensor, dict) and _positive(sensor.get(k)))]
    bad += [f"servo.{k}" for k in ("shape_c", "frequency_hz", "amplitude_rad")
            if not (isinstance(servo, dict) and _finite(servo.get(k)))]
    if not bad:
        try:
            stated_angle_sigma_rad(header)
        except ValueError as e:
            return f"{e}, so the beams' pointing error between samples is unknown"
    what = ", ".join(bad) if bad else "a usable sample rate and servo waveform"
    return f"the log header lacks {what}, so the beam's step between samples is unknown"


def _finite(v: object) -> bool:
    return not isinstance(v, bool) and isinstance(v, int | float) and math.isfinite(v)


def _positive(v: object) -> bool:
    return _finite(v) and v > 0  # type: ignore[operator]


def spike_mask(t_s: np.ndarray, range_m: np.ndarray, usable: np.ndarray, threshold: SpikeThreshold,
               pairs: bool = True) -> np.ndarray:
    """True for usable samples that are isolated one-sample (and, with pairs, two-sample) spikes.

    Only usable samples with finite t and r take part; the others are never spikes, and a gap of
    more than MAX_GAP_PERIODS sample periods breaks the chain of time-neighbours. Thresholds are
    evaluated only for the few local extrema beyond T's least value (2-3 ms for 64k samples).
    """
    t = np.asarray(t_s, dtype=float)
    r = np.asarray(range_m, dtype=float)
    out = np.zeros(len(t), dtype=bool)
    idx = np.flatnonzero(np.asarray(usable, dtype=bool) & np.isfinite(t) & np.isfinite(r))
    if len(idx) < 3:
        return out
    tu = t[idx]
    if np.any(np.diff(tu) < 0):  # logs are written in time order; sort defensively
        idx = idx[np.argsort(tu, kind="stable")]
        tu = t[idx]
    ru = r[idx]
    dt = np.diff(tu)
    link = dt <= MAX_GAP_PERIODS * threshold.sample_period_s  # link[j]: samples j and j+1 are neighbours
    spike = np.zeros(len(idx), dtype=bool)

    floor = float(threshold(0.0, 0.0))  # T's least value: only samples beyond it get the exact test

    # one sample m between a and b: T for the longer of its two spans, A for the span a-b
    da, db = ru[1:-1] - ru[:-2], ru[1:-1] - ru[2:]
    j = np.flatnonzero(link[:-1] & link[1:] & (da * db > 0) & (np.minimum(np.abs(da), np.abs(db)) > floor))
    a, b = ru[j], ru[j + 2]
    rs = 0.5 * (a + b)
    tol = threshold(rs, np.maximum(dt[j], dt[j + 1]))
    single = ((np.abs(a - b) <= threshold.agree(rs, dt[j] + dt[j + 1]))
              & (np.abs(da[j]) > tol) & (np.abs(db[j]) > tol))
    spike[j[single] + 1] = True

    if pairs and len(idx) >= 4:  # two samples m1, m2 between a and b, which agree within T
        a, m1, m2, b = ru[:-3], ru[1:-2], ru[2:-1], ru[3:]
        d = [m1 - a, m1 - b, m2 - a, m2 - b]
        j = np.flatnonzero(link[:-2] & link[1:-1] & link[2:] & (d[0] * d[1] > 0) & (d[2] * d[3] > 0)
                           & (np.minimum(np.minimum(np.abs(d[0]), np.abs(d[1])),
                                         np.minimum(np.abs(d[2]), np.abs(d[3]))) > floor))
        tol = threshold(0.5 * (a[j] + b[j]), np.maximum(np.maximum(dt[j], dt[j + 1]), dt[j + 2]))
        pair = np.abs(a[j] - b[j]) <= tol
        for dk in d:
            pair &= np.abs(dk[j]) > tol
        spike[j[pair] + 1] = True
        spike[j[pair] + 2] = True

    out[idx[spike]] = True
    return out
