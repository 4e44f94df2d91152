"""Isolated range spikes (ground.despike): removed where no surface could put them, kept everywhere else."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.header import build_log_header, sensor_spec
from firmware_py.core.samplelog import SampleFlags, SampleLog, new_records
from firmware_py.core.storage import Storage
from firmware_py.core.waveform import Waveform, frequency_for_peak_rate
from ground.despike import MAX_GAP_PERIODS, SpikeThreshold, spike_mask, why_no_threshold
from ground.pointcloud import cloud_from_samples
from ground.report import ReportOptions, summarise, survey_from_samples

RATE_HZ = 500.0
WAVEFORM = Waveform(shape_c=0.95, frequency_hz=frequency_for_peak_rate(5.0, 0.95))  # Table 1: 5 rad/s peak
STORAGE = Storage(60, 40, 15)


def _header(waveform: Waveform = WAVEFORM, **sensor) -> dict:
    return build_log_header(source="test", sensor=sensor_spec(RATE_HZ, **sensor), lever_arm_body_m=[0, 0, 0],
                            waveform_name="semi-triangular", waveform=waveform, initial_position=0,
                            storage=STORAGE, frame=StorageFrame())


THRESHOLD = SpikeThreshold.from_header(_header())


CREST_X, CREST_Z, WALL_X = 12.0, 6.0, 30.0
SLOPE = math.tan(math.radians(40))


def _sweep_ranges(seconds: float = 40.0, noise_sigma: bool = True, seed: int = 0, pointing_sigma_rad: float = 0.0):
    """Times, ranges and usability of a beam swept by the Table 1 servo from 12 m across a 2D section
    (floor; a pile at its 40 deg angle of repose, crest 6 m high at x = 12; a wall at x = 30), the
    vehicle flying along it at 1 m/s. Noise at the header's sigma (2.5 cm, 1 % of range), 1 cm
    quantisation; hits beyond 40 m are no return (not usable). pointing_sigma_rad: each sample's beam
    off its commanded angle by a white error (Appendix A's servo noise)."""
    t = np.arange(int(seconds * RATE_HZ)) / RATE_HZ
    gamma = WAVEFORM.angle(t) + np.random.default_rng(seed + 100).normal(size=len(t)) * pointing_sigma_rad
    x0, dx, dz = t * 1.0, np.sin(gamma), -np.cos(gamma)
    with np.errstate(divide="ignore", invalid="ignore"):
        # the ray (x0 + s dx, 12 + s dz) against each piece of the section, kept where the hit lies on it
        s_floor = -12.0 / dz
        x_floor = x0 + s_floor * dx
        floor = np.where(np.abs(x_floor - CREST_X) >= CREST_Z / SLOPE, s_floor, np.inf)
        faces = []
        for side in (1.0, -1.0):  # z = CREST_Z - side * SLOPE * (x - CREST_X)
            s_face = (CREST_Z - 12.0 - side * SLOPE * (x0 - CREST_X)) / (dz + side * SLOPE * dx)
            dxc = x0 + s_face * dx - CREST_X
            faces.append(np.where((side * dxc >= 0) & (side * dxc <= CREST_Z / SLOPE), s_face, np.inf))
        s_wall = (WALL_X - x0) / dx
        wall = np.where(12.0 + s_wall * dz >= 0, s_wall, np.inf)
        cand = np.stack([floor, *faces, wall])
        r = np.min(np.where(cand > 0, cand, np.inf), axis=0)
    usable = r <= 40.0
    r = np.where(usable, r, 0.0)
    if noise_sigma:
        rng = np.random.default_rng(seed)
        r = r + rng.normal(size=len(r)) * np.maximum(0.025, 0.01 * r)
    return t, np.round(r * 100) / 100, usable


def test_that_the_threshold_is_derived_from_the_header():
    th = THRESHOLD
    assert th.sample_period_s == pytest.approx(1 / RATE_HZ)
    assert float(th.step_rad()) == pytest.approx((5.0 + 1.0) / RATE_HZ)  # servo peak + body allowance
    # 4 sigma of a two-sample difference (sigma = 1 % of 12 m) + 1 cm + a plane at 45 deg over one step
    step = 6.0 / RATE_HZ
    geometry = 12.0 * (math.cos(math.pi / 4) / math.cos(math.pi / 4 + step) - 1)
    assert float(th(12.0)) == pytest.approx(4 * math.sqrt(2) * 0.12 + 0.01 + geometry)
    assert float(th(12.0)) == pytest.approx(0.836, abs=0.005)
    assert float(th(2.0)) == pytest.approx(4 * math.sqrt(2) * 0.025 + 0.01 + 2 * geometry / 12)  # sigma floor
    # A: the same noise, a plane at 80 deg over the two steps from a to b
    a = 12.0 * (math.cos(math.radians(80)) / math.cos(math.radians(80) + 2 * step) - 1)
    assert float(th.agree(12.0, 2 / RATE_HZ)) == pytest.approx(4 * math.sqrt(2) * 0.12 + 0.01 + a)
    # a quieter sensor and a slower servo give a tighter threshold
    quiet = SpikeThreshold.from_header(_header(range_sigma_m=0.01, range_sigma_rel=0.0))
    slow = SpikeThreshold.from_header(_header(Waveform(shape_c=0.95, frequency_hz=frequency_for_peak_rate(1.0, 0.95))))
    assert float(quiet(12.0)) < float(th(12.0)) and float(slow(12.0)) < float(th(12.0))


def test_that_the_geometric_allowance_alone_keeps_a_noiseless_crest_wall_foot_and_floor():
    t, r, usable = _sweep_ranges(noise_sigma=False)
    geometry_only = SpikeThreshold(THRESHOLD.sample_period_s, THRESHOLD.beam_rate_rad_s, n_sigma=0.0)
    assert not spike_mask(t, r, usable, geometry_only).any()
    # ... and it is needed: with no allowance every range extremum (the floor straight below, the crest,
    # the wall foot) would be a "spike"
    none = SpikeThreshold(THRESHOLD.sample_period_s, THRESHOLD.beam_rate_rad_s, n_sigma=0.0, max_turn_rad=0.0)
    assert spike_mask(t, r, usable, none).sum() > 10


@pytest.mark.parametrize("seed", [0, 1])
def test_that_noise_at_the_header_sigma_is_left_alone(seed):
    t, r, usable = _sweep_ranges(seed=seed)
    assert usable.sum() > 15_000
    assert not spike_mask(t, r, usable, THRESHOLD).any()


def test_that_injected_single_spikes_and_pairs_are_removed_and_nothing_else():
    t, r, usable = _sweep_ranges(seed=2)
    rng = np.random.default_rng(3)
    true = r.copy()
    # where a and b (i - 1 and i + 2) could tell: usable and on a surface flat enough that they agree
    j = np.arange(1, len(r) - 2)
    ok = usable[j - 1] & usable[j] & usable[j + 1] & usable[j + 2]
    cand = j[ok & (np.abs(r[j + 2] - r[j - 1]) < 0.5 * THRESHOLD(r[j - 1]))]
    picks = rng.choice(cand, 60, replace=False)
    picks = picks[np.min(np.abs(picks[:, None] - picks[None, :]) + 10 * np.eye(len(picks), dtype=int), axis=1) > 4]
    singles, pairs = picks[::2], picks[1::2]
    for i in np.concatenate([singles, pairs, pairs + 1]):
        while abs(r[i] - true[i]) <= 3 * float(THRESHOLD(true[i])):  # a garbage read, clear of the surface
            r[i] = rng.uniform(0.02, 60.0)
    found = spike_mask(t, r, usable, THRESHOLD)
    expected = np.zeros(len(r), dtype=bool)
    expected[np.concatenate([singles, pairs, pairs + 1])] = True
    assert np.array_equal(found, expected)
    # without the pair test the pairs stay
    assert np.array_equal(spike_mask(t, r, usable, THRESHOLD, pairs=False), found & ~np.isin(np.arange(len(r)),
                                                                                            np.r_[pairs, pairs + 1]))


def test_that_a_stated_per_sample_pointing_error_is_not_taken_for_spikes():
    """Appendix A's 1 deg white servo error puts three consecutive beams out of order, so on a slope the
    middle one stands out from both neighbours: a header that states it widens T to what a plane at up to
    a_max allows; gross faults are still removed."""
    sigma = math.radians(1.0)
    t, r, usable = _sweep_ranges(seed=4, pointing_sigma_rad=sigma)
    stated = SpikeThreshold.from_header({**_header(), "sensor_noise": {"model": "appendix-a", "servo_sigma_rad": sigma,
                                                                       "attitude_sigma_rad": 0.0}})
    assert stated.angle_sigma_rad == pytest.approx(sigma)
    assert spike_mask(t, r, usable, THRESHOLD).sum() > 50  # unstated, the jitter passes for spikes
    assert not spike_mask(t, r, usable, stated).any()
    below = np.flatnonzero(usable & (np.abs(WAVEFORM.angle(t)) < 0.05))[5::400][:10]  # the floor straight below
    r[below] = 59.0
    assert np.array_equal(np.flatnonzero(spike_mask(t, r, usable, stated)), below)


def test_that_steps_that_persist_are_kept():
    t = np.arange(40) / RATE_HZ
    usable = np.ones(40, dtype=bool)
    step = np.r_[np.full(20, 10.0), np.full(20, 16.0)]
    assert not spike_mask(t, step, usable, THRESHOLD).any()
    # an edge with a mixed return between the two surfaces, and a two-sample ledge between two others
    mixed = step.copy()
    mixed[20] = 13.0
    assert not spike_mask(t, mixed, usable, THRESHOLD).any()
    ledge = np.r_[np.full(19, 10.0), 13.0, 13.0, np.full(19, 16.0)]
    assert not spike_mask(t, ledge, usable, THRESHOLD).any()
    # a spike right at the edge is not isolated (its neighbours disagree): kept too, by design
    at_edge = step.copy()
    at_edge[19] = 30.0
    assert not spike_mask(t, at_edge, usable, THRESHOLD).any()
    # but the same value one sample away from the edge is removed
    inside = step.copy()
    inside[10] = 30.0
    assert np.flatnonzero(spike_mask(t, inside, usable, THRESHOLD)).tolist() == [10]


def test_that_gaps_decide_who_is_a_neighbour():
    n = 30
    t = np.arange(n) / RATE_HZ
    r = np.full(n, 12.0)
    r[10] = r[20] = 25.0
    usable = np.ones(n, dtype=bool)
    usable[9] = False  # one flagged sample before the spike at 10: its neighbours are 8 and 11
    usable[[18, 19]] = False  # two before the one at 20: no left neighbour, not judged
    assert np.flatnonzero(spike_mask(t, r, usable, THRESHOLD)).tolist() == [10]
    assert MAX_GAP_PERIODS < 3
    # flagged and non-finite samples are never spikes themselves
    usable[10] = False
    r[15] = np.nan
    assert not spike_mask(t, r, usable, THRESHOLD).any()


def test_that_an_unusable_header_turns_despiking_off():
    h = _header()
    assert SpikeThreshold.from_header({**h, "servo": None}) is None
    assert SpikeThreshold.from_header({**h, "sensor": {**h["sensor"], "rate_hz": 0}}) is None
    assert SpikeThreshold.from_header({**h, "servo": {**h["servo"], "frequency_hz": "fast"}}) is None
    assert SpikeThreshold.from_header({}) is None
    bad_noise = {**h, "sensor_noise": {"model": "appendix-a", "servo_sigma_rad": -1.0}}
    assert SpikeThreshold.from_header(bad_noise) is None
    assert "sensor_noise.servo_sigma_rad" in why_no_threshold(bad_noise)
    with pytest.raises(ValueError, match="sample_period_s"):
        SpikeThreshold(0.0, 6.0)


def _floor_survey_samples(spike_at: int | None) -> np.ndarray:
    """A hall floor swept from 12 m (no pile), with one 6 m reading (a point 6 m up) at spike_at."""
    n = 10_000
    s = new_records(n)
    s["t_s"] = np.arange(n) / RATE_HZ
    s["x_m"], s["y_m"], s["z_m"] = 10.0 + s["t_s"], -20.0, -12.0
    s["servo_rad"] = np.clip(WAVEFORM.angle(s["t_s"]), -0.95, 0.95)
    s["sweep_dir"] = WAVEFORM.sweep_direction(s["t_s"])
    s["range_m"] = np.round(12.0 / np.cos(s["servo_rad"]) * 100) / 100
    if spike_at is not None:
        s["range_m"][spike_at] = 6.0
    return s


def test_that_the_survey_leaves_spikes_out_counts_them_and_can_keep_them():
    s = _floor_survey_samples(spike_at=5000)
    s["flags"][100] = SampleFlags.NO_RETURN
    h = _header()
    lever = np.zeros(3)
    on = survey_from_samples(s, h, STORAGE, StorageFrame(), lever, ReportOptions(plots=False))
    off = survey_from_samples(s, h, STORAGE, StorageFrame(), lever, ReportOptions(plots=False, despike=False))
    assert ReportOptions().despike
    assert on.cloud.n_spikes == 1 and on.cloud.n_excluded == 2
    assert off.cloud.n_spikes == 0 and off.cloud.n_excluded == 1
    assert len(off.cloud.points_w) == len(on.cloud.points_w) + 1
    assert np.nanmax(off.heights_fit) < 1.0  # the default fit's own outlier test leaves the spike out too ...
    through = ReportOptions(plots=False, despike=False, surface_fit="cubic-limited")  # ... a fit through every point
    kept = survey_from_samples(s, h, STORAGE, StorageFrame(), lever, through)
    assert np.nanmax(kept.heights_fit) > 1.0 > np.nanmax(on.heights_fit)  # does not: the despiking took it out
    log = SampleLog(h, s, 1, 0, 0, 0)
    rep = summarise(on, log, ReportOptions(plots=False), None)
    assert rep["n_samples_spikes"] == 1 and rep["despike"] is True
    assert any(w.startswith("1 isolated range spikes left out") for w in rep["warnings"])
    rep_off = summarise(off, log, ReportOptions(plots=False, despike=False), None)
    assert rep_off["n_samples_spikes"] == 0 and not any("spike" in w for w in rep_off["warnings"])


def test_that_a_clean_survey_loses_nothing():
    s = _floor_survey_samples(spike_at=None)
    c = cloud_from_samples(s, np.zeros(3), StorageFrame(), spike_threshold=THRESHOLD)
    assert c.n_spikes == 0 and c.n_excluded == 0


def test_that_datasheet_noise_and_its_no_returns_trigger_neither_despiking_nor_plausibility():
    from firmware_py.core.sensor import LIDARLITE_V3
    from firmware_py.core.sensor_noise import SensorNoise
    from firmware_py.core.waveform import named_waveform
    from ground.plausibility import PlausibilityLimits, implausible
    from sitl.sensing.batch_sampler import sample_flight
    from sitl.vehicle.ideal_plant import Trajectory
    from sitl.world.raycast import World

    n = 60_000  # two minutes hovering mid-hall at 12 m: the sweep sees the floor and, at its ends, far walls
    pos = np.tile([20.0, -15.0, -12.0], (n, 1))
    z = np.zeros(n)
    traj = Trajectory(np.arange(n) / 500.0, pos, z, z, z + 0.3)
    wf, storage, frame = named_waveform("semi-triangular"), Storage(), StorageFrame()
    noise = SensorNoise.of("datasheet", LIDARLITE_V3)
    s = sample_flight(traj, wf, World(storage), LIDARLITE_V3, (0.0, 0.0, 0.1), frame, noise=noise, seed=11)
    assert ((s["flags"] & int(SampleFlags.NO_RETURN)) != 0).mean() > 0.1  # the no-returns are there
    header = build_log_header(source="test", sensor=LIDARLITE_V3.to_dict(), lever_arm_body_m=(0, 0, 0.1),
                              waveform_name="semi-triangular", waveform=wf, initial_position=0, storage=storage,
                              frame=frame, extra={"sensor_noise": noise.record()})
    usable = (s["flags"] & int(SampleFlags.NO_RETURN)) == 0
    assert spike_mask(s["t_s"], s["range_m"], usable, SpikeThreshold.from_header(header)).sum() == 0
    assert implausible(s, PlausibilityLimits.from_header(header, storage), frame).counts() == \
        {"servo_angle": 0, "range": 0, "pose": 0}
