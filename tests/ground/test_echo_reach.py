"""The samples without an echo, traced to where they aimed: beyond the rangefinder's reach, or not."""

import math

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleFlags, new_records
from firmware_py.core.sensor import LIDARLITE_V3
from firmware_py.core.storage import Storage
from ground.echo_reach import bare_building_hits, echo_reach, echo_record, echo_warning, sensor_returns
from ground.render import fmt_echo
from ground.surface import Grid

STORAGE = Storage(60.0, 40.0, 15.0)
FRAME = StorageFrame((0.0, 0.0, 0.0), math.pi / 2)  # W: x east, y north; heading 0 sweeps the beam along W x
GRID = Grid(60.0, 40.0, 0.25)
HEADER = {"sensor": LIDARLITE_V3.to_dict()}  # 40 m on a 70 % target; 30 % ground assumed: 26.2 m at normal incidence


def _samples(servo_deg, flags=SampleFlags.NO_RETURN, x_m=10.0):
    """Beams from W (x_m, 20, 12), heading north, at these servo angles (positive: towards +x, from nadir)."""
    s = new_records(len(servo_deg))
    s["x_m"], s["y_m"], s["z_m"] = 20.0, x_m, -12.0  # NED: north 20, east x_m, 12 m up
    s["servo_rad"] = np.radians(servo_deg)
    s["flags"] = flags
    return s


def test_that_a_beam_aimed_beyond_reach_marks_the_floor_past_its_sure_reach_and_no_nearer():
    # 60 deg from nadir: the floor 24 m away at x = 30.8 m, met at cos i = 0.5, where the sure reach is
    # 0.9 x 40 x sqrt(0.5 x 0.3 / 0.7) = 16.7 m (x = 24.4 m): the cells from there to the floor are out of reach
    r = echo_reach(_samples([60.0]), HEADER, [0, 0, 0], FRAME, STORAGE, GRID)
    assert (r.n_aimed, r.n_no_echo, r.n_beyond_reach) == (1, 1, 1)
    ix, iy = np.nonzero(r.out_of_reach)
    x = (ix + 0.5) * 0.25
    assert x.min() == pytest.approx(10 + 16.665 * math.sin(math.radians(60)), abs=0.25)
    assert x.max() == pytest.approx(10 + 12 * math.tan(math.radians(60)), abs=0.25)
    assert set(iy) == {80}  # y = 20 m: the beam's own row
    assert r.reach_normal_m == pytest.approx(0.9 * 40 * math.sqrt(0.3 / 0.7))


def test_that_a_beam_within_reach_and_samples_with_an_echo_or_without_a_pose_mark_nothing():
    near = echo_reach(_samples([0.0, 20.0]), HEADER, [0, 0, 0], FRAME, STORAGE, GRID)  # the floor 12-13 m away
    assert (near.n_no_echo, near.n_beyond_reach) == (2, 0) and not near.out_of_reach.any()
    echoed = echo_reach(_samples([60.0], SampleFlags.NONE), HEADER, [0, 0, 0], FRAME, STORAGE, GRID)
    assert (echoed.n_aimed, echoed.n_no_echo) == (1, 0) and not echoed.out_of_reach.any()
    unposed = echo_reach(_samples([60.0], SampleFlags.NO_RETURN | SampleFlags.STALE_POSE), HEADER, [0, 0, 0], FRAME,
                         STORAGE, GRID)
    assert unposed is None  # nothing could be traced
    outside = _samples([60.0], x_m=-5.0)  # 5 m outside the wall x = 0: a damaged record, no survey beam
    assert echo_reach(outside, HEADER, [0, 0, 0], FRAME, STORAGE, GRID) is None


def test_that_a_sensor_without_a_known_return_model_or_a_malformed_header_gives_no_diagnosis():
    other = {"sensor": {**LIDARLITE_V3.to_dict(), "model": "some other rangefinder"}}
    assert echo_reach(_samples([60.0]), other, [0, 0, 0], FRAME, STORAGE, GRID) is None
    assert sensor_returns({"sensor": "not a record"}) is None and sensor_returns({}) is None


def test_that_the_headers_stated_return_model_is_the_one_used():
    """A simulated survey states its return assumptions in sensor_noise; a darker ground reaches less far."""
    dark = {**HEADER, "sensor_noise": {"reference_reflectance": 0.7, "target_reflectance": 0.1,
                                       "dropout_ramp_rel": 0.1}}
    assert sensor_returns(dark)[1].target_reflectance == 0.1
    r = echo_reach(_samples([30.0]), dark, [0, 0, 0], FRAME, STORAGE, GRID)  # 13.9 m to the floor
    assert r.n_beyond_reach == 1  # beyond 0.9 x 40 x sqrt(0.866 x 0.1 / 0.7) = 12.7 m
    assert echo_reach(_samples([30.0]), HEADER, [0, 0, 0], FRAME, STORAGE, GRID).n_beyond_reach == 0


def test_that_the_bare_building_is_left_through_the_plane_the_beam_meets_first():
    o = np.array([[10.0, 20.0, 12.0]] * 3)
    d = np.array([[0.0, 0.0, -1.0], [1.0, 0.0, 0.0], [0.6, 0.0, -0.8]])
    dist, cos_i = bare_building_hits(o, d, STORAGE)
    assert dist == pytest.approx([12.0, 50.0, 15.0])  # the floor, the wall x = 60, the floor again
    assert cos_i == pytest.approx([1.0, 1.0, 0.8])


def _record(fill_m3, term=None):
    heights_fit = np.zeros(GRID.shape)
    heights_fit[:40, :] = np.nan  # a 10 m strip along the wall x = 0, never seen
    heights = np.where(np.isfinite(heights_fit), 0.0, fill_m3 / (40 * GRID.shape[1] * GRID.cell_area_m2))
    # from x = 28 m, 70 deg from nadir towards the wall x = 0, met 29.8 m away beyond its 22.8 m sure reach there
    r = echo_reach(_samples([-70.0], x_m=28.0), HEADER, [0, 0, 0], FRAME, STORAGE, GRID)
    return echo_record(r, heights_fit, heights, GRID, term)


def test_that_the_warning_speaks_when_the_interval_it_holds_matters_and_names_where():
    seen = []
    rec = _record(400.0, lambda cells: seen.append(cells.copy()) or 50.0)  # the interval allows +/-50 m³ for it
    assert rec["unseen_out_of_reach_m2"] > 0 and rec["fill_out_of_reach_m3"] > 0 and rec["unseen_term_m3"] == 50.0
    assert seen[0].sum() * GRID.cell_area_m2 == rec["unseen_out_of_reach_m2"]  # asked over the out-of-reach cells
    assert not seen[0][40:].any()  # and only unseen ones
    w = echo_warning(rec, 1000.0, 5.0)  # 5 % of the volume: more than half of a 5 % tolerance
    assert w is not None and "beyond the Garmin LIDAR-Lite v3's reach" in w and "x 0-" in w and "+/-50 m³" in w
    assert echo_warning(rec, 3000.0, 5.0) is None  # 1.7 %: less than half of it
    assert echo_warning(None, 1000.0, 5.0) is None and echo_warning(_record(400.0), 1000.0, 5.0) is None


def test_that_the_line_says_how_many_had_no_echo_and_why():
    rec = _record(1.0)
    assert fmt_echo(rec).startswith("1 of 1 samples without an echo (100.0 %); 1 of them aimed beyond")
    assert fmt_echo({"samples_aimed": 10, "no_echo": 0}) == "0 of 10 samples without an echo (0.0 %)"
    assert fmt_echo({"no_echo": "x"}) == "unknown"


def test_that_a_simulated_sensor_without_a_return_model_reaches_its_range_at_any_incidence():
    """The SITL's ideal rangefinder has no echo only beyond its max_range_m; a real one's log (any other source) is
    judged by the datasheet's return model."""
    simulated = {**HEADER, "source": "sitl/jsbsim"}
    near = echo_reach(_samples([60.0]), simulated, [0, 0, 0], FRAME, STORAGE, GRID)  # the floor 24 m away: in range
    assert near.n_beyond_reach == 0 and near.target_reflectance is None and near.reach_normal_m == 40.0
    far = echo_reach(_samples([-80.0], x_m=50.0), simulated, [0, 0, 0], FRAME, STORAGE, GRID)  # the wall x = 0, 50.8 m
    assert far.n_beyond_reach == 1
    assert "the simulated Garmin LIDAR-Lite v3's range (40 m at any incidence)" in fmt_echo(
        echo_record(far, np.zeros(GRID.shape), np.zeros(GRID.shape), GRID))
    real = echo_reach(_samples([60.0]), {**HEADER, "source": "payload"}, [0, 0, 0], FRAME, STORAGE, GRID)
    assert real.n_beyond_reach == 1 and real.target_reflectance == 0.3
