"""The networked SITL end to end: `pilescan-sitl serve --devices`, `pilescan-payload --hal sitl:` and a
scripted ground station as three processes on real sockets, in real time (about 10-15 s each)."""

import numpy as np
import pytest

from firmware_py.core.frames import StorageFrame, beam_rays_w
from firmware_py.core.samplelog import EXCLUDE_FROM_CLOUD, SampleFlags, read_samplelog
from firmware_py.core.storage import Storage
from sitl.world import stockpile as piles
from sitl.world.raycast import World
from tools.fly_networked import fly_networked

pytestmark = pytest.mark.long  # scheduled first (tests/conftest.py)


def range_errors(log, world: World, good: np.ndarray, posed: np.ndarray,
                 frame: StorageFrame | None = None) -> np.ndarray:
    """|logged range of `good` - the served world's range| with each range tagged by the pose and servo angle of
    `posed` (good itself, or good shifted to tag each range with a later sample's pose), placed through `frame`
    (None: the default storage frame)."""
    o, d = beam_rays_w(np.column_stack([posed["x_m"], posed["y_m"], posed["z_m"]]), posed["roll_rad"],
                       posed["pitch_rad"], posed["yaw_rad"], posed["servo_rad"],
                       np.array(log.header["lever_arm_body_m"]), frame or StorageFrame())
    err = np.abs(good["range_m"][:len(posed)] - world.cast(o, d).range_m)
    return err[np.isfinite(err)]


def test_that_the_payload_process_ranges_the_served_world_with_correct_pose_tags(tmp_path):
    storage = Storage(24, 16, 10)
    run = fly_networked(["--p-traj", "25", "--altitude", "9", "--speed", "2"], "24x16x10", "1", tmp_path / "net",
                        flight_s=8.0, say=lambda _m: None)
    assert run.payload_exit == 0  # SIGTERM: a clean stop
    log = read_samplelog(tmp_path / "net" / "samples.pslog")
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 0
    s = log.samples
    # At most one sample per 2 ms slot of the loop's 500 Hz grid, in time order, from well before take-off to
    # the stop. No lower bound on the rate: a starved machine (the suite's workers and three processes on
    # 2 cores) misses slots, and both a sample count and the median interval measured the machine (they
    # failed at load 6.5 and on CI). That the loop keeps its grid when it misses slots is shown in
    # tests/firmware_py/test_payload_seams.py on a simulated clock.
    assert np.all(np.diff(s["t_s"]) > 0)
    assert len(s) < (s["t_s"][-1] - s["t_s"][0]) / 0.002 + 2  # + 2: the first may run up to a slot late
    # Logging from before take-off: the first posed sample on the floor (it climbs below). Not a span of the 8 s
    # flown: the stamps are real time, and a payload starved of the CPU in the second before its SIGTERM (the suite's
    # workers, serve and this test on 2 cores) ended its log 7.7 s after its first sample.
    posed = s[(s["flags"] & int(SampleFlags.NO_POSE | SampleFlags.STALE_POSE)) == 0]
    assert -posed["z_m"][0] < 0.5
    good = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    assert len(good) > 0.5 * len(s)
    assert np.ptp(good["servo_rad"]) > np.radians(120)  # the servo swept
    assert np.ptp(good["z_m"]) > 3.0  # and the vehicle climbed while we logged
    # Each logged pose and servo angle, ray traced in the served world, gives the range measured.
    world = World(storage, piles.resolve(str(tmp_path / "net" / "pile.stl"), storage))
    err = range_errors(log, world, good, good)
    # The median and the tail against the same ranges tagged one 2 ms slot late (the beam sweeps the pile fast: 7.8
    # cm at the 90th percentile on an idle machine, where the tags' own is 1.6 cm): each range is tagged with its own
    # slot when it is nearer none than that, below half of it. The stamps are real time, and a starved machine (the
    # suite's workers and two campaigns on 2 cores) stretched the tail to 3.0 cm, past a fixed 3 cm; a slower machine
    # (2026-12-01) put the median at 0.7-1.2 cm, past a fixed 1 cm, with one slot late at 2.4-6.1 cm.
    one_slot_late = range_errors(log, world, good, good[1:])
    assert np.median(err) < np.median(one_slot_late) / 2
    assert np.percentile(err, 90) < np.percentile(one_slot_late, 90) / 2
    assert run.report["volume_m3"] > 0


def test_that_a_signed_networked_flight_works_with_the_key_on_every_link_and_the_bridge(tmp_path):
    key_file = tmp_path / "link.key"
    key_file.write_text("ab" * 32 + "\n")
    key_file.chmod(0o600)
    run = fly_networked(["--p-traj", "25", "--altitude", "9", "--speed", "2"], "24x16x10", "1", tmp_path / "net",
                        flight_s=4.0, say=lambda _m: None, signing_key=key_file)
    assert run.payload_exit == 0
    s = read_samplelog(tmp_path / "net" / "samples.pslog").samples
    good = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    assert len(good) > 500  # signed poses arrived and tagged samples


def test_that_the_payload_reads_a_served_tfmini_over_a_pty_and_survives_its_faults(tmp_path):
    """serve --rangefinder tfmini streams frames into a pseudo-terminal; the payload process reads them with
    pyserial. Bad frames and a 2 s unplug (from 4 s after AUTO) end as flagged samples; the ranges it
    keeps match the served world from their logged poses; after the replug it ranges again."""
    storage = Storage(30, 20, 10)
    run = fly_networked(["--p-traj", "25", "--altitude", "9", "--speed", "2"], "30x20x10", "1", tmp_path / "net",
                        flight_s=12.0, say=lambda _m: None, rangefinder="tfmini",
                        serve_args=["--fault", "tfmini_bad_frame_pct=3", "--fault", "tfmini_unplug=4,2"])
    assert run.payload_exit == 0
    log = read_samplelog(tmp_path / "net" / "samples.pslog")
    assert log.blocks_corrupt == 0 and log.blocks_truncated == 0
    assert log.header["payload"]["uart"].startswith("serial:/dev/")
    s = log.samples
    assert np.median(np.diff(s["t_s"])) == pytest.approx(0.01, abs=2e-4)  # paced by the 100 Hz frames
    err_flag = (s["flags"] & int(SampleFlags.SENSOR_ERROR)) != 0
    # The unplugged window: the longest run of flagged samples lasts the 2 s (timeouts every 30 ms).
    runs = np.split(np.flatnonzero(err_flag), np.flatnonzero(np.diff(np.flatnonzero(err_flag)) > 1) + 1)
    longest = max(runs, key=len)
    unplugged_s = s["t_s"][longest[-1]] - s["t_s"][longest[0]]
    assert unplugged_s >= 1.7 and unplugged_s <= 3.0  # real time: a busy machine may stretch it
    assert len(runs) > 5  # and the bad frames, one flagged sample each, scattered
    after = s[longest[-1] + 1:]
    assert np.count_nonzero((after["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0) > 200  # ranging again
    good = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    world = World(storage, piles.resolve(str(tmp_path / "net" / "pile.stl"), storage), max_range_m=12.0)
    err = range_errors(log, world, good, good)
    # A range tagged one frame (10 ms) late puts the tail at decimetres (the beam sweeps the pile fast). The
    # frames' stamps are real time: on a busy machine some arrive a few ms late, so the median and the tail are
    # held to a third of that reference, derived from this flight, rather than to a number of centimetres (a
    # median held to 1 cm failed at 1.004 cm with the suite's three workers on two cores, where one frame late
    # gave 8.8 cm).
    one_frame_late = range_errors(log, world, good, good[1:])
    assert len(err) > 300 and np.median(err) < np.median(one_frame_late) / 3
    assert np.percentile(err, 90) < np.percentile(one_frame_late, 90) / 3


def test_that_a_networked_flight_at_a_turned_site_agrees_on_origin_and_frame(tmp_path):
    """serve and the payload both given --origin -33.9,151.2,30 --heading 30: the payload's EKF origin is
    confirmed, not refused, its header carries the site and the turned frame, and the ranges it logged,
    ray traced from its logged poses through that frame in the served world, are the ranges measured."""
    from pymavlink import mavutil

    from firmware_py.core.site import Site

    storage = Storage(24, 16, 10)
    site = Site.of(-33.9, 151.2, 30.0, 30.0)
    run = fly_networked(["--p-traj", "25", "--altitude", "9", "--speed", "2"], "24x16x10", "1", tmp_path / "net",
                        flight_s=6.0, say=lambda _m: None,
                        site_args=["--origin=-33.9,151.2,30", "--heading=30"])
    assert run.payload_exit == 0
    log = read_samplelog(tmp_path / "net" / "samples.pslog")
    assert log.header["site"] == site.to_dict()
    frame = StorageFrame.from_dict(log.header["storage_frame"])
    assert frame == site.frame_about()
    tlog = mavutil.mavlink_connection(str(tmp_path / "net" / "telemetry.tlog"), dialect="ardupilotmega")
    origins, refusals = [], []
    while (m := tlog.recv_match(type=["GPS_GLOBAL_ORIGIN", "STATUSTEXT"])) is not None:
        if m.get_type() == "GPS_GLOBAL_ORIGIN":
            origins.append((m.latitude, m.longitude, m.altitude))
        elif "origin" in m.text.lower():
            refusals.append(m.text)
    assert origins and set(origins) == {(-339_000_000, 1_512_000_000, 30_000)} and refusals == []
    s = log.samples
    good = s[(s["flags"] & int(EXCLUDE_FROM_CLOUD)) == 0]
    assert len(good) > 500
    world = World(storage, piles.resolve(str(tmp_path / "net" / "pile.stl"), storage))
    err = range_errors(log, world, good, good, frame)
    # The median and the tail held to half those of the same ranges tagged one 2 ms slot late, as in the first test:
    # a fixed 3 cm tail and a fixed 1 cm median measured the machine (3.008 cm with the suite and a second test run on
    # the 2 cores; a median of 1.17 cm on a slower machine, 2026-12-01, where one slot late gives 2.4-6.1 cm).
    one_slot_late = range_errors(log, world, good, good[1:], frame)
    assert np.median(err) < np.median(one_slot_late) / 2
    assert np.percentile(err, 90) < np.percentile(one_slot_late, 90) / 2


def test_that_the_flight_waits_for_the_payloads_first_block_and_not_for_an_older_log(tmp_path):
    """A fixed sleep raced the payload's start-up on a loaded machine; the wait is on what the payload wrote."""
    import subprocess
    import sys

    from firmware_py.core.samplelog import SAMPLE_DTYPE, SampleLogWriter
    from tools.fly_networked import _stamp, wait_logging

    log = tmp_path / "samples.pslog"
    with SampleLogWriter(log, {"note": "an older flight's"}, records_per_block=1, fsync=False) as w:
        w.append(np.zeros(1, dtype=SAMPLE_DTYPE))
    proc = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(30)"])
    try:
        with pytest.raises(RuntimeError, match=r"logged no posed sample within 0\.5 s"):
            wait_logging(log, proc, 0.5, _stamp(log))  # the older log does not count
        log.unlink()
        unposed = np.zeros(3, dtype=SAMPLE_DTYPE)
        unposed["flags"] = int(SampleFlags.NO_POSE)
        with SampleLogWriter(log, {"note": "this flight's"}, records_per_block=1, fsync=False) as w:
            w.append(unposed)  # the time sync still converging: no pose yet
            with pytest.raises(RuntimeError, match=r"logged no posed sample within 0\.5 s"):
                wait_logging(log, proc, 0.5, None)
            w.append(np.zeros(1, dtype=SAMPLE_DTYPE))
        wait_logging(log, proc, 5.0, None)  # returns: a posed sample is there
    finally:
        proc.kill()
        proc.wait()
    done = subprocess.Popen([sys.executable, "-c", "pass"])
    done.wait()
    with pytest.raises(RuntimeError, match="payload exited early"):
        wait_logging(tmp_path / "none.pslog", done, 5.0, None)
