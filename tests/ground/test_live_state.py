"""The live page's running state (`ground.live_state`): returns placed and binned as records arrive, the track,
the running volume by the report's own computation, the caps, and the state without a building."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from firmware_py.core.samplelog import SampleFlags, new_records, read_samplelog
from ground.listen import load_header
from ground.live_state import (
    STALE_AFTER_S,
    LiveGeometry,
    LiveOptions,
    LiveState,
    VolumeState,
    map_cell_m,
)
from tests.ground.test_report_fuzz import BASE_HEADER

GOLDEN = Path(__file__).resolve().parents[1] / "golden"


class Clock:
    def __init__(self) -> None:
        self.t = 100.0

    def __call__(self) -> float:
        return self.t


def state(header: dict | None = BASE_HEADER, clock: Clock | None = None, counters: dict | None = None,
          **opts) -> LiveState:
    geo = None if header is None else LiveGeometry.from_header(header, "test header")
    return LiveState(geo, lambda: dict(counters or {"records": 0}), opts=LiveOptions(**opts),
                     geometry_problem=None if header else "no --header", clock=clock or Clock())


def hover(n: int, north: float, east: float, height: float, range_m: float, flags: int = 0) -> np.ndarray:
    """n records of a level vehicle at (north, east, height) looking straight down (servo 0)."""
    r = new_records(n)
    r["t_s"] = np.arange(n) * 0.002
    r["x_m"], r["y_m"], r["z_m"] = north, east, -height
    r["range_m"], r["servo_rad"], r["sweep_dir"], r["flags"] = range_m, 0.0, 1, flags
    return r


def cell(snap: dict, x: float, y: float) -> float | None:
    m = snap["map"]
    i, j = int(x / snap["storage"]["length_m"] * m["nx"]), int(y / snap["storage"]["width_m"] * m["ny"])
    return m["z_m"][i * m["ny"] + j]


def test_that_a_downward_return_lands_in_its_cell_at_its_height():
    """Vehicle at NED (10, -6, -6), i.e. W (10, 6, 6); sensor 0.10 m below the centre of gravity; 5.4 m down:
    the point is at W z = 6 - 0.1 - 5.4 = 0.5 m, in the cell over (10, 6), and nowhere else."""
    live = state()
    live.offer(hover(50, 10.0, -6.0, 6.0, 5.4))
    assert live.snapshot()["map"]["points_pct"] == 0.0  # handed over, not yet taken: the receiver did no work
    assert live.accumulate() == 50
    snap = live.snapshot()
    assert cell(snap, 10.0, 6.0) == pytest.approx(0.5, abs=0.005)
    assert sum(z is not None for z in snap["map"]["z_m"]) == 1
    assert snap["map"]["unseen_pct"] == pytest.approx(100.0 - snap["map"]["points_pct"])  # no surface yet
    assert snap["position"] == pytest.approx([10.0, 6.0, 6.0])
    assert snap["frame"] == "storage" and snap["track"][0] == pytest.approx([10.0, 6.0])


def test_that_flagged_records_place_no_point_and_unvouched_poses_draw_no_track():
    live = state()
    live.offer(hover(20, 10.0, -6.0, 6.0, 5.4, flags=int(SampleFlags.NO_RETURN)))
    live.offer(hover(20, 0.0, 0.0, 0.0, 5.4, flags=int(SampleFlags.NO_POSE)))  # a zero pose: not a place
    live.accumulate()
    snap = live.snapshot()
    assert snap["map"]["points_pct"] == 0.0 and snap["map"]["n_points"] == 0
    assert snap["track"] == [[10.0, 6.0]] and snap["position"] == pytest.approx([10.0, 6.0, 6.0])


def test_that_walls_and_roof_stay_off_the_map():
    live = state()
    live.offer(hover(10, 10.0, -6.0, 6.0, 6.0 - 0.1))  # the floor itself: z = 0
    wall = hover(10, 10.0, -6.0, 6.0, 6.0)
    wall["servo_rad"] = np.pi / 2  # to starboard (W -y for a vehicle facing north): the wall y = 0 at 6 m
    live.offer(wall)
    live.accumulate()
    snap = live.snapshot()
    assert snap["map"]["n_points"] == 20  # the wall's returns were placed ...
    assert sum(z is not None for z in snap["map"]["z_m"]) == 1  # ... and removed: the floor's cell only


def test_that_the_map_built_batch_by_batch_is_the_map_of_the_whole_log():
    samples = read_samplelog(GOLDEN / "samples.pslog").samples
    header = load_header(GOLDEN / "samples.pslog")
    whole, parts = state(header), state(header)
    whole.offer(samples)
    whole.accumulate()
    for i in range(0, len(samples), 37):
        parts.offer(samples[i:i + 37])
        if i % 370 == 0:
            parts.accumulate()
    parts.accumulate()
    a, b = whole.snapshot()["map"], parts.snapshot()["map"]
    assert a["n_points"] == b["n_points"] > 1000
    assert a["z_m"] == b["z_m"] and 10.0 < a["points_pct"] < 100.0


def test_that_the_running_volume_is_the_reports_volume_and_interval_on_the_same_records():
    """The golden log: the report (with its self-calibration and servo re-timing, which change nothing on it)
    said what tests/golden/report_figures.json holds; the live page's computation on the same records, streamed
    in batches, says the same."""
    samples = read_samplelog(GOLDEN / "samples.pslog").samples
    figures = json.loads((GOLDEN / "report_figures.json").read_text())
    live = state(load_header(GOLDEN / "samples.pslog"))
    assert live.snapshot()["volume"]["state"] == VolumeState.WAITING.value
    for i in range(0, len(samples), 500):
        live.offer(samples[i:i + 500])
        live.accumulate()
    live.compute_volume()
    v = live.snapshot()["volume"]
    assert v["state"] == VolumeState.OK.value and v["records"] == len(samples)
    assert v["volume_m3"] == pytest.approx(figures["volume_m3"], rel=1e-9)
    assert v["coverage_ratio_pct"] == pytest.approx(figures["coverage_ratio_pct"], rel=1e-9)
    lo, hi = v["interval_m3"]
    assert lo < v["volume_m3"] < hi
    assert v["age_s"] == 0.0 and v["compute_s"] >= 0.0
    # The unseen cells are now those without a surface: about what R_a misses, far fewer than cells without points.
    m = live.snapshot()["map"]
    assert m["unseen_pct"] == pytest.approx(100.0 - figures["coverage_ratio_pct"], abs=3.0)
    assert m["unseen_pct"] < 100.0 - m["points_pct"] - 30.0


def test_that_too_few_records_give_a_reason_not_a_volume():
    live = state()
    live.offer(hover(5, 10.0, -6.0, 6.0, 5.4))
    live.accumulate()
    live.compute_volume()
    v = live.snapshot()["volume"]
    assert v["state"] == VolumeState.NOT_YET.value and v["volume_m3"] is None and v["why"]


def test_that_the_volumes_records_are_capped_but_the_map_keeps_growing():
    live = state(max_volume_records=30)
    live.offer(hover(20, 10.0, -6.0, 6.0, 5.4))
    live.offer(hover(20, 15.0, -6.0, 6.0, 5.4))
    live.accumulate()
    snap = live.snapshot()
    assert snap["volume"]["records_kept"] == 30 and snap["volume"]["capped"] is True
    assert snap["map"]["n_points"] == 40 and cell(snap, 15.0, 6.0) is not None


def test_that_a_long_track_is_thinned_and_keeps_its_ends():
    live = state(max_track_points=50)
    for k in range(200):
        r = hover(5, 1.0 + 0.05 * k, -6.0, 6.0, 5.4)
        r["t_s"] = k * 1.0 + np.arange(5) * 0.002
        live.offer(r)
        live.accumulate()
    track = live.snapshot()["track"]
    assert 25 <= len(track) <= 50
    assert track[0] == pytest.approx([1.0, 6.0]) and track[-1][0] > 1.0 + 0.05 * 190


def test_that_a_stopped_stream_is_stale_after_a_few_seconds():
    clock = Clock()
    live = state(clock=clock)
    assert live.snapshot()["since_last_records_s"] is None and not live.snapshot()["stale"]
    live.offer(hover(5, 10.0, -6.0, 6.0, 5.4))
    clock.t += STALE_AFTER_S / 2
    assert not live.snapshot()["stale"]
    clock.t += STALE_AFTER_S
    snap = live.snapshot()
    assert snap["stale"] and snap["since_last_records_s"] == pytest.approx(1.5 * STALE_AFTER_S)


def test_that_the_rate_is_taken_from_the_receivers_count():
    clock, counters = Clock(), {"records": 0}
    live = state(clock=clock, counters=counters)
    live.accumulate()
    clock.t += 2.0
    counters["records"] = 1000
    live.accumulate()
    assert live.snapshot()["counters"] == {"records": 1000, "rate_hz": pytest.approx(500.0)}


def test_that_without_a_building_there_are_counters_and_a_north_up_track_only():
    live = state(None)
    live.offer(hover(5, 3.0, 4.0, 2.0, 1.5))
    live.accumulate()
    live.compute_volume()
    snap = live.snapshot()
    assert snap["frame"] == "ned" and snap["map"] is None and snap["storage"] is None
    assert snap["track"] == [[3.0, 4.0]] and snap["position"] == pytest.approx([3.0, 4.0, 2.0])
    assert snap["volume"]["state"] == VolumeState.NO_GEOMETRY.value and snap["geometry_problem"] == "no --header"


def test_that_a_header_without_the_building_is_a_one_line_error():
    from firmware_py.core.cli import UserError
    with pytest.raises(UserError, match="storage") as exc:
        LiveGeometry.from_header({"software": "x"}, "header from h.json")
    assert "\n" not in str(exc.value)


def test_that_the_snapshot_is_strict_json_and_the_map_cell_suits_the_building():
    live = state()
    live.offer(hover(5, 10.0, -6.0, 6.0, 5.4))
    live.accumulate()
    body = json.loads(live.snapshot_json())  # strict: no NaN or Infinity
    assert body["map"]["cell_m"] == map_cell_m(live.geometry.storage)
    from firmware_py.core.storage import Storage
    assert map_cell_m(Storage(60, 40, 15)) == pytest.approx(0.5)
    assert map_cell_m(Storage(24, 16, 10)) == pytest.approx(0.25)
    assert map_cell_m(Storage(400, 100, 20)) == pytest.approx(3.35)


def test_that_random_records_leave_the_map_and_track_in_the_building_and_warn_of_nothing():
    """Records of random bytes (a forged, unauthenticated stream), half of them "no return": nothing lands
    outside the building, no numpy warning is raised (it would print over listen's status line), the snapshot
    stays strict JSON."""
    import warnings

    from firmware_py.core.samplelog import SAMPLE_DTYPE
    rng = np.random.default_rng(1)
    live = state()
    for _ in range(10):
        r = np.frombuffer(rng.integers(0, 256, SAMPLE_DTYPE.itemsize * 500, dtype=np.uint8).tobytes(),
                          dtype=SAMPLE_DTYPE).copy()
        r["flags"] = np.where(np.arange(len(r)) % 2, int(SampleFlags.NO_RETURN), 0)  # no return: still a pose
        live.offer(r)
    live.offer(hover(5, 10.0, -6.0, 6.0, 5.4))
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a warning would end the step: the worker keeps it as its error
        live._survive(live.accumulate)
        live._survive(live.compute_volume)
    assert live.worker_error is None
    snap = json.loads(live.snapshot_json())
    lo, hi = live._limits.pose_lo_w_m, live._limits.pose_hi_w_m
    assert snap["track"] and all(lo[0] <= x <= hi[0] and lo[1] <= y <= hi[1] for x, y in snap["track"])
    assert snap["position"] == pytest.approx([10.0, 6.0, 6.0])
    assert cell(snap, 10.0, 6.0) == pytest.approx(0.5, abs=0.005)


def test_that_a_worker_survives_an_error_and_the_page_is_told():
    live = state()
    live.offer(np.zeros(3, dtype=[("x", "f8")]))  # not records at all: the step fails
    assert live._survive(live.accumulate) is None
    assert live.worker_error.startswith(("ValueError", "KeyError")) and live.snapshot()["worker_error"]
    live.offer(hover(5, 10.0, -6.0, 6.0, 5.4))
    live._survive(live.accumulate)
    assert cell(live.snapshot(), 10.0, 6.0) == pytest.approx(0.5, abs=0.005)  # and goes on
