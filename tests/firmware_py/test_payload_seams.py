"""The payload loop's typed seams: reading statuses are ReadStatus members, poses are PoseSamples, and
what the loop counts comes out as a frozen LoopStats snapshot."""

import math
from dataclasses import FrozenInstanceError

import numpy as np
import pytest

from firmware_py.core.samplelog import SampleFlags
from firmware_py.core.waveform import named_waveform
from firmware_py.drivers.lidarlite import Reading, ReadStatus
from firmware_py.drivers.servo import SweepServo
from firmware_py.hal.clock import SimClock
from firmware_py.payload import COUNTED_FLAGS, LoopConfig, LoopStats, PayloadLoop
from firmware_py.pose import PoseSample

NAN3 = (math.nan, math.nan, math.nan)
FRESH = PoseSample(0, (1.0, 2.0, -3.0), 0.1, -0.2, 0.3, 0.01, stale=False, missing=False)
OLD = PoseSample(0, NAN3, math.nan, math.nan, math.nan, 0.5, stale=True, missing=False)
MISSING = PoseSample(0, NAN3, math.nan, math.nan, math.nan, math.inf, stale=True, missing=True)


class NullPwm:
    def set_pulse_us(self, pulse_us):
        pass

    def disable(self):
        pass

    def close(self):
        pass


class CannedSensor:
    """Hands out readings of the given statuses, stamped with the clock."""

    def __init__(self, clock, statuses):
        self.clock, self.statuses = clock, list(statuses)

    def read(self):
        status = self.statuses.pop(0)
        return Reading(12.5 if status is ReadStatus.OK else None, status, self.clock.now_ns(), 1)


class CannedPose:
    def __init__(self, pose):
        self.pose = pose

    def pump(self):
        pass

    def pose_at(self, t_ns):
        return self.pose


class RecordingLog:
    def __init__(self):
        self.records = []

    def append(self, record):
        self.records.append(record)

    def flush(self):
        pass


def run(statuses, pose=FRESH):
    clock = SimClock()
    log = RecordingLog()
    loop = PayloadLoop(CannedSensor(clock, statuses), SweepServo(NullPwm(), named_waveform("semi-triangular")),
                       CannedPose(pose), clock, log, LoopConfig(max_pose_wait_s=0.001))
    for _ in statuses:
        clock.sleep_until_ns(clock.now_ns() + 2_000_000)
        loop.tick()
    loop.run(duration_s=0.0)  # flushes what waits for a pose
    return loop, np.array(log.records)


def test_that_an_ok_reading_with_a_fresh_pose_is_logged_unflagged_with_that_pose():
    _, recs = run([ReadStatus.OK])
    assert recs["flags"].tolist() == [0] and recs["range_m"].tolist() == [12.5]
    assert (recs["x_m"][0], recs["y_m"][0], recs["z_m"][0]) == FRESH.pos_ned_m


@pytest.mark.parametrize(("status", "flag"), [
    (ReadStatus.NO_RETURN, SampleFlags.NO_RETURN), (ReadStatus.TIMEOUT, SampleFlags.SENSOR_ERROR),
    (ReadStatus.BUS_ERROR, SampleFlags.SENSOR_ERROR), (ReadStatus.RESETTING, SampleFlags.SENSOR_ERROR)])
def test_that_each_failed_status_gets_its_flag_and_no_range(status, flag):
    loop, recs = run([status])
    assert recs["flags"].tolist() == [int(flag)] and recs["range_m"].tolist() == [0.0]
    assert loop.stats.flagged(flag) == 1


@pytest.mark.parametrize(("pose", "flag"), [(OLD, SampleFlags.STALE_POSE), (MISSING, SampleFlags.NO_POSE)])
def test_that_a_stale_or_missing_pose_is_flagged_and_never_tags_the_sample(pose, flag):
    loop, recs = run([ReadStatus.OK], pose)
    assert recs["flags"].tolist() == [int(flag)]
    assert loop.stats.flagged(SampleFlags.STALE_POSE | SampleFlags.NO_POSE) == 1


def test_that_the_loop_stats_are_a_frozen_snapshot_counting_every_flag():
    loop, _ = run([ReadStatus.OK, ReadStatus.NO_RETURN, ReadStatus.TIMEOUT, ReadStatus.TIMEOUT], MISSING)
    stats = loop.stats
    assert stats.ticks == 4
    assert stats.flagged(SampleFlags.SENSOR_ERROR) == 2 and stats.flagged(SampleFlags.NO_RETURN) == 1
    assert stats.flagged(SampleFlags.NO_POSE) == 4
    assert stats.as_dict()["flagged"] == {"NO_RETURN": 1, "STALE_POSE": 0, "NO_POSE": 4, "SENSOR_ERROR": 2,
                                          "SERVO_UNCERTAIN": 0}
    with pytest.raises(FrozenInstanceError):
        stats.ticks = 0


def test_that_a_fresh_loop_stats_counts_nothing():
    assert LoopStats().flagged(SampleFlags(sum(COUNTED_FLAGS))) == 0 and LoopStats().as_dict()["ticks"] == 0


def test_that_a_pose_sample_cannot_be_changed_or_grown():
    with pytest.raises(FrozenInstanceError):
        FRESH.stale = True
    assert not hasattr(FRESH, "__dict__")  # slots: no attribute can be probed into existence


class StallingSensor(CannedSensor):
    """Stamps each reading, then stalls the loop (a starved CPU, a slow bus) on the reads named."""

    def __init__(self, clock, stalls_ns):
        super().__init__(clock, [])
        self.stalls_ns, self.n = stalls_ns, 0

    def read(self):
        reading = Reading(12.5, ReadStatus.OK, self.clock.now_ns(), 1)
        self.clock.advance_by_ns(self.stalls_ns.get(self.n, 0))
        self.n += 1
        return reading


def test_that_a_run_started_late_samples_its_whole_duration_on_its_grid_and_misses_no_tick():
    """Between t0 (the sweep's origin, in the header) and the loop's start the program opens its log and greets the
    autopilot; on a loaded computer that took longer than a short run, which then logged nothing (`--duration 0.4`
    with no sample), and the wait counted as missed ticks."""
    clock, log = SimClock(), RecordingLog()
    period_ns = 2_000_000
    loop = PayloadLoop(StallingSensor(clock, {}), SweepServo(NullPwm(), named_waveform("semi-triangular")),
                       CannedPose(FRESH), clock, log, LoopConfig(rate_hz=500.0))  # t0 = 0
    clock.advance_by_ns(700_300_000)  # a slow fsync, say
    stats = loop.run(duration_s=0.2)
    assert stats.overruns == 0 and abs(stats.ticks - 0.2 * 1e9 / period_ns) <= 2  # 0.2 s of ticks, none missed
    t_ns = np.array([round(r["t_s"] * 1e9) for r in log.records])
    assert t_ns[0] == 700_300_000 and (t_ns[1:] % period_ns == 0).all()  # then back on the grid from t0
    assert t_ns[-1] - t_ns[0] == pytest.approx(0.2e9, abs=period_ns)


def test_that_a_stalled_loop_counts_the_slots_it_missed_and_keeps_its_tick_grid():
    clock, log = SimClock(), RecordingLog()
    period_ns = 2_000_000
    sensor = StallingSensor(clock, {10: 7_300_000, 30: 2_500_000})  # 3.6 and 1.25 periods late
    loop = PayloadLoop(sensor, SweepServo(NullPwm(), named_waveform("semi-triangular")), CannedPose(FRESH),
                       clock, log, LoopConfig(rate_hz=500.0))
    stats = loop.run(duration_s=0.2)
    slots = 0.2 * 1e9 / period_ns + 1  # from 0 to 0.2 s, both ends
    assert stats.overruns == 2  # the 22 and 24 ms slots; 2.5 ms late misses no whole slot
    assert stats.ticks + stats.overruns == slots
    t_ns = np.array([round(r["t_s"] * 1e9) for r in log.records])
    off_grid = t_ns % period_ns != 0
    assert off_grid.sum() == 2  # the one late tick after each stall; every other sample is in phase
    assert t_ns[-1] == 0.2 * 1e9
