"""The interval's warnings on flown surveys: each fires on a pile that needs it and stays quiet on a clean one."""

from __future__ import annotations

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame
from firmware_py.core.samplelog import SampleLog
from firmware_py.core.storage import Storage
from ground.report import ReportOptions, summarise, survey_from_samples
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, log_header
from sitl.sensing.batch_sampler import sample_flight
from sitl.vehicle.ideal_plant import IdealPlant
from sitl.world.raycast import World
from sitl.world.shapes import make_shape

STORAGE = Storage(30.0, 20.0, 10.0)


def _report(family: str, p_traj: float, seed: int = 0) -> dict:
    """A survey of the family's pile of that seed (top <= 6 m) flown at 8 m by the ideal plant, summarised."""
    shape = make_shape(family, STORAGE, 6.0, seed)
    cfg = FlyConfig(mission=Mission(storage=STORAGE, altitude_m=8.0, p_traj=p_traj))
    plant = IdealPlant(cfg.mission, StorageFrame())
    t = np.arange(int(plant.duration_s * cfg.lidar.rate_hz) + 1) / cfg.lidar.rate_hz
    wf = cfg.servo_waveform()
    samples = sample_flight(plant.states(t), wf, World(STORAGE, shape.pile, cfg.lidar.max_range_m), cfg.lidar,
                            cfg.lever_arm_body_m, cfg.frame, seed=[0])
    header = log_header(cfg, wf)
    opts = ReportOptions(plots=False)
    sv = survey_from_samples(samples, header, STORAGE, cfg.frame, np.array(cfg.lever_arm_body_m), opts)
    log = SampleLog(header=header, samples=samples, blocks_ok=1, blocks_corrupt=0, blocks_truncated=0, bytes_skipped=0)
    return summarise(sv, log, opts, shape.pile.volume_m3)


def _interval_warnings(rep: dict) -> list[str]:
    return [w for w in rep["warnings"] if "never seen" in w or "vertical face" in w or "interval is" in w]


def test_that_a_corner_pile_flown_sparsely_warns_of_material_in_the_unseen_corner():
    # seed 3 at P_traj 30 %: 22 m² of its corner unseen, the unseen term about twice the interpolation term in
    # a ±6 % interval. (Seed 0 at 40 %, this test's case before the interval's 2026-11-28 recalibration, now has
    # the two terms about equal in a ±3 % interval: no single cause holds most of it, and the warning says so by
    # staying quiet.)
    rep = _report("corner", 0.30, seed=3)
    unseen = [w for w in rep["warnings"] if "never seen" in w]
    assert len(unseen) == 1 and "x 0-" in unseen[0] and "y 0-" in unseen[0]  # the pile's corner, at the origin
    lo, hi = rep["volume_interval_m3"]
    assert lo <= rep["true_volume_m3"] <= hi


def test_that_a_box_warns_of_vertical_faces():
    rep = _report("box", 0.05)
    assert any("vertical face" in w for w in rep["warnings"])


@pytest.mark.parametrize("family", ["cone", "corner"])
def test_that_a_densely_flown_pile_has_a_tight_interval_and_no_interval_warning(family):
    rep = _report(family, 0.05)
    assert _interval_warnings(rep) == []
    lo, hi = rep["volume_interval_m3"]
    assert lo <= rep["true_volume_m3"] <= hi and (hi - lo) / 2 < 0.01 * rep["true_volume_m3"]
