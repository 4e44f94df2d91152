"""Fuzzing the MAVLink receive path: the payload's `ByteStreamLink` / `MavlinkFramer`, the `PoseTracker` on top
of it, and the SITL autopilot's `MavlinkVehicleServer`. Whatever bytes arrive (noise, bit-flipped or truncated
frames, frames full of NaN), nothing raises, every valid frame after the damage is recovered, and the damage is
counted.

Byte accounting (the framer's contract): once enough trailing bytes have arrived to settle every candidate header,
each byte fed is either inside a delivered frame or counted in `rx_bad_bytes`.
"""

from __future__ import annotations

import itertools
import math
from importlib.util import find_spec

import pytest
from hypothesis import HealthCheck, assume, given
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from firmware_py.hal.clock import SimClock
from firmware_py.hal.mavlink_link import ByteStreamLink, MavlinkFramer
from firmware_py.pose_tracker import PoseTracker
from tests.fuzz_budget import budget

SIM = find_spec("sitl") is not None  # False on the payload-only install (Raspberry Pi): those tests skip
if SIM:
    from sitl.mavlink.server import MavlinkVehicleServer
    from sitl.mavlink.transport import PipeTransport
    from sitl.vehicle.kinematic_vehicle import KinematicVehicle
needs_sim = pytest.mark.skipif(not SIM, reason="needs the simulator (sitl/), not in the payload-only install")

FUZZ = budget(200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
SLOW_FUZZ = budget(100, deadline=None, suppress_health_check=[HealthCheck.too_slow])

FLUSH = bytes(300)
"""More than the longest frame (280 bytes) of non-magic bytes: settles any header the damage left open."""

u8 = st.integers(0, 255)
u16 = st.integers(0, 2**16 - 1)
u32 = st.integers(0, 2**32 - 1)
i32 = st.integers(-(2**31), 2**31 - 1)
i64 = st.integers(-(2**63), 2**63 - 1)
f32 = st.floats(width=32)  # NaN and infinities included
param_id = st.binary(max_size=16)

POSE_MESSAGES = st.one_of(
    st.builds(mavlink.MAVLink_attitude_message, u32, f32, f32, f32, f32, f32, f32),
    st.builds(mavlink.MAVLink_local_position_ned_message, u32, f32, f32, f32, f32, f32, f32),
    st.builds(mavlink.MAVLink_heartbeat_message, u8, u8, u8, u32, u8, u8),
    st.builds(mavlink.MAVLink_timesync_message, i64, i64),
    st.builds(mavlink.MAVLink_command_ack_message, u16, u8, u8, i32, u8, u8),
    st.builds(mavlink.MAVLink_system_time_message, st.integers(0, 2**64 - 1), u32),
)
"""What an autopilot sends the payload, with any field values."""

SOURCES = st.sampled_from([(1, 1), (1, 1), (1, 1), (1, 191), (2, 1), (255, 190)])


@st.composite
def frames(draw, messages=POSE_MESSAGES, min_size: int = 1, max_size: int = 12) -> list[bytes]:
    """Valid MAVLink 1 and 2 frames, each from its own source and sequence number."""
    out = []
    for msg in draw(st.lists(messages, min_size=min_size, max_size=max_size)):
        sysid, compid = draw(SOURCES)
        mav = mavlink.MAVLink(None, srcSystem=sysid, srcComponent=compid)
        mav.seq = draw(u8)
        out.append(bytes(msg.pack(mav, force_mavlink1=draw(st.booleans()))))
    return out


garbage = st.one_of(
    st.binary(max_size=300),
    st.lists(st.one_of(st.sampled_from([0xFD, 0xFE, 0x00, 0x01, 0xFF]), u8), max_size=300).map(bytes),
)
"""Noise, some of it dense in MAVLink start markers (each one a false frame header to reject)."""


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    """data split at the given (sorted, deduplicated) offsets."""
    edges = [0, *sorted({c % (len(data) + 1) for c in cuts}), len(data)]
    return [data[a:b] for a, b in itertools.pairwise(edges) if b > a]


class Feed:
    """recv_bytes/send_bytes for a ByteStreamLink: queued chunks out one per call; sent bytes kept."""

    def __init__(self, chunks: list[bytes] = ()) -> None:
        self.chunks = list(chunks)
        self.sent = bytearray()

    def recv(self) -> bytes:
        return self.chunks.pop(0) if self.chunks else b""

    def send(self, data: bytes) -> None:
        self.sent += data


def receive_all(chunks: list[bytes]) -> tuple[list, ByteStreamLink]:
    feed = Feed(chunks)
    link = ByteStreamLink(feed.send, feed.recv)
    got = []
    for _ in range(len(chunks)):
        got += link.recv()
    return got, link


def check_accounting(got: list, link: ByteStreamLink, total: int) -> None:
    s = link.stats
    assert s["rx_bytes"] == total and s["rx_messages"] == len(got)
    assert s["rx_bad_bytes"] + sum(len(m.get_msgbuf()) for m in got) == total
    assert s["rx_bad_frames"] <= s["rx_bad_bytes"]
    assert s["io_errors"] == 0 and link.last_error is None


def buffers(msgs: list) -> list[bytes]:
    return [bytes(m.get_msgbuf()) for m in msgs]


# ----- the payload's link -------------------------------------------------------------------------------

@FUZZ
@given(data=st.binary(max_size=2000), cuts=st.lists(st.integers(0, 2000), max_size=8))
def test_that_random_bytes_never_raise_and_every_byte_is_accounted_for(data, cuts):
    got, link = receive_all(chunked(data + FLUSH, cuts))
    check_accounting(got, link, len(data) + len(FLUSH))


@FUZZ
@given(noise=st.lists(st.tuples(garbage, frames(max_size=3)), min_size=1, max_size=6),
       cuts=st.lists(st.integers(0, 4000), max_size=10))
def test_that_every_valid_frame_after_garbage_is_recovered_in_order(noise, cuts):
    """Garbage, frames, garbage, frames...: the frames come out, in order, however the stream is cut."""
    stream = b"".join(g + b"".join(fs) for g, fs in noise)
    valid = [f for _, fs in noise for f in fs]
    got, link = receive_all(chunked(stream + FLUSH, cuts))
    check_accounting(got, link, len(stream) + len(FLUSH))
    assert _subsequence(valid, buffers(got))
    if noise[-1][1]:  # nothing after the last frames but the flush: they are the last ones out
        assert buffers(got)[-len(noise[-1][1]):] == noise[-1][1]


def _subsequence(needles: list[bytes], hay: list[bytes]) -> bool:
    """needles appear in hay in order (hay may hold extra frames only if noise happened to be one)."""
    it = iter(hay)
    return all(any(n == h for h in it) for n in needles)


@FUZZ
@given(data=st.data(), good=frames(min_size=2, max_size=10))
def test_that_a_frame_with_one_flipped_bit_is_dropped_and_the_others_survive(data, good):
    damaged = data.draw(st.sets(st.integers(0, len(good) - 1), min_size=1), label="damaged frames")
    stream = []
    for k, f in enumerate(good):
        if k in damaged:
            bit = data.draw(st.integers(0, 8 * len(f) - 1), label=f"bit of frame {k}")
            f = bytearray(f)
            f[bit // 8] ^= 1 << (bit % 8)
        stream.append(bytes(f))
    total = b"".join(stream) + FLUSH
    got, link = receive_all(chunked(total, data.draw(st.lists(st.integers(0, len(total)), max_size=6))))
    check_accounting(got, link, len(total))
    assert buffers(got) == [f for k, f in enumerate(good) if k not in damaged]  # CRC-16 catches any 1-bit error
    assert link.stats["rx_bad_bytes"] > 0


@FUZZ
@given(data=st.data(), good=frames(min_size=2, max_size=10))
def test_that_truncated_frames_cost_only_themselves(data, good):
    cut = data.draw(st.sets(st.integers(0, len(good) - 2), min_size=1), label="truncated frames")
    parts = [f[:data.draw(st.integers(1, len(f) - 1), label=f"keep of {k}")] if k in cut else f
             for k, f in enumerate(good)]
    for k in cut:  # a frame cut just before bytes equal to the ones it lost is whole again: not a truncation
        assume(not b"".join(parts[k + 1:]).startswith(good[k][len(parts[k]):]))
    stream = b"".join(parts)
    got, link = receive_all([stream + FLUSH])
    check_accounting(got, link, len(stream) + len(FLUSH))
    assert buffers(got) == [f for k, f in enumerate(good) if k not in cut]


@FUZZ
@given(head=garbage, good=frames(min_size=1, max_size=8))
def test_that_frames_held_behind_an_open_header_come_out_once_later_bytes_settle_it(head, good):
    """Noise may end in a header claiming up to 280 bytes: the frames behind it wait (whole, in order) for
    enough bytes to reject it, and none is ever delivered in part."""
    stream = head + b"".join(good)
    feed = Feed([stream])
    link = ByteStreamLink(feed.send, feed.recv)
    first = link.recv()
    feed.chunks.append(FLUSH)
    rest = link.recv()
    assert _subsequence(good, buffers(first + rest))
    assert buffers(first + rest)[-len(good):] == good
    check_accounting(first + rest, link, len(stream) + len(FLUSH))


# ----- the pose tracker on top of it --------------------------------------------------------------------

class Autopilot:
    """Answers the tracker's TIMESYNC requests (so it converges and starts buffering poses) with a fixed offset,
    then lets the fuzzer's bytes through."""

    def __init__(self, offset_ns: int) -> None:
        self.offset_ns = offset_ns
        self.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
        self.framer = MavlinkFramer()

    def replies(self, sent: bytes) -> bytes:
        out = bytearray()
        for m in self.framer.feed(sent):
            if m.get_type() == "TIMESYNC" and m.tc1 == 0:
                reply = mavlink.MAVLink_timesync_message(m.ts1 + self.offset_ns, m.ts1)
                out += reply.pack(self.mav)
                self.mav.seq = (self.mav.seq + 1) % 256
        return bytes(out)


@SLOW_FUZZ
@given(steps=st.lists(st.tuples(st.integers(0, 200_000_000), st.one_of(garbage, frames(max_size=4).map(b"".join))),
                      min_size=1, max_size=40),
       offset_ns=st.integers(-(10**15), 10**15), warmup=st.integers(0, 15))
def test_that_the_pose_tracker_never_raises_on_whatever_decodes(steps, offset_ns, warmup):
    """After `warmup` clean exchanges (12 converge the time sync, so poses are buffered), anything goes."""
    clock = SimClock(start_ns=10**12)
    feed = Feed()
    link = ByteStreamLink(feed.send, feed.recv)
    tracker = PoseTracker(link, clock)
    tracker.start()
    ap = Autopilot(offset_ns)
    n_sent = 0
    for k in range(warmup + len(steps)):
        if k == warmup and warmup >= 12:
            assert tracker.timesync.converged
        dt_ns, fuzz = steps[k - warmup] if k >= warmup else (100_000_000, b"")
        clock.advance_by_ns(dt_ns)
        feed.chunks.append(ap.replies(bytes(feed.sent[n_sent:])) + fuzz)
        n_sent = len(feed.sent)
        tracker.pump()
    status = tracker.status()
    assert status.link == link.stats and status.tracker["tx_timesync"] >= 1
    assert link.stats["tx_errors"] == 0
    buf = tracker.buffer.stats
    assert buf["positions"] + buf["attitudes"] + buf["rejected_nonfinite"] <= link.stats["rx_messages"]
    pose = tracker.pose_at(clock.now_ns())
    assert pose.usable or math.isnan(pose.roll_rad)


# ----- the SITL autopilot's receive side ----------------------------------------------------------------

f64ish = st.one_of(f32, st.sampled_from([0.0, 1.0, -1.0, 2.0, 3.0, 4.0, 21196.0, 1e6, -1e6]))
commands = st.one_of(st.sampled_from([400, 22, 300, 176, 511, 510, 512, 520, 410, 183, 178, 16, 21]), u16)
GCS_MESSAGES = st.one_of(
    st.builds(mavlink.MAVLink_heartbeat_message, u8, u8, u8, u32, u8, u8),
    st.builds(mavlink.MAVLink_timesync_message, i64, i64),
    st.builds(mavlink.MAVLink_command_long_message, st.sampled_from([0, 1, 7]), st.sampled_from([0, 1, 5]),
              commands, u8, f64ish, f64ish, f64ish, f64ish, f64ish, f64ish, f64ish),
    st.builds(mavlink.MAVLink_command_int_message, st.sampled_from([0, 1]), st.sampled_from([0, 1]), u8, commands,
              u8, u8, f64ish, f64ish, f64ish, f64ish, i32, i32, f64ish),
    st.builds(mavlink.MAVLink_set_mode_message, st.sampled_from([0, 1, 3]), u8, u32),
    st.builds(mavlink.MAVLink_param_set_message, st.just(1), st.just(1),
              st.one_of(param_id, st.sampled_from([b"PS_SPEED_MS", b"PS_ALT_M", b"PS_YAW_RATE_DPS"])), f32, u8),
    st.builds(mavlink.MAVLink_param_request_read_message, st.just(1), st.just(1), param_id, st.integers(-1, 40)),
    st.builds(mavlink.MAVLink_param_request_list_message, st.just(1), st.just(1)),
    st.builds(mavlink.MAVLink_mission_count_message, st.just(1), st.just(1), u16, st.sampled_from([0, 1, 2, 255])),
    st.builds(mavlink.MAVLink_mission_item_int_message, st.just(1), st.just(1), st.integers(0, 5),
              st.sampled_from([0, 1, 3, 5, 6, 2, 99]), st.sampled_from([16, 21, 22, 178, 177, 0]), u8, u8,
              f64ish, f64ish, f64ish, f64ish, i32, i32, f64ish, st.sampled_from([0, 1])),
    st.builds(mavlink.MAVLink_mission_item_message, st.just(1), st.just(1), st.integers(0, 5),
              st.sampled_from([0, 3, 1]), st.sampled_from([16, 21, 22, 178]), u8, u8,
              f64ish, f64ish, f64ish, f64ish, f64ish, f64ish, f64ish, st.just(0)),
    st.builds(mavlink.MAVLink_mission_request_int_message, st.just(1), st.just(1), u16, st.sampled_from([0, 1])),
    st.builds(mavlink.MAVLink_mission_request_list_message, st.just(1), st.just(1), st.sampled_from([0, 1, 2])),
    st.builds(mavlink.MAVLink_mission_clear_all_message, st.just(1), st.just(1), st.sampled_from([0, 1])),
    st.builds(mavlink.MAVLink_mission_ack_message, st.just(1), st.just(1), u8, st.just(0)),
)
"""What a ground station (or a confused one) sends the autopilot, with any field values."""


@needs_sim
@SLOW_FUZZ
@given(chunks=st.lists(st.one_of(garbage, frames(GCS_MESSAGES, max_size=6).map(b"".join)), min_size=1,
                       max_size=25))
def test_that_the_sitl_autopilot_never_raises_counts_the_damage_and_no_handler_fails(chunks):
    server_end, client_end = PipeTransport.pair()
    vehicle = KinematicVehicle(speed_m_s=2.0, yaw_rate_max_rad_s=math.radians(90), altitude_m=2.0)
    server = MavlinkVehicleServer(vehicle, server_end)
    reference = MavlinkFramer()
    expected = []
    for chunk in [*chunks, FLUSH]:
        client_end.send(chunk)
        expected += reference.feed(chunk)
        vehicle.step()
        server.update()
        client_end.recv()  # the telemetry it answers with: not the point here
    s = server.stats
    assert s["rx_messages"] == len(expected) == sum(s["rx_by_type"].values())
    assert (s["rx_bad_bytes"], s["rx_parse_errors"]) == (reference.bad_bytes, reference.bad_frames)
    total = sum(map(len, chunks)) + len(FLUSH)
    assert s["rx_bad_bytes"] + sum(len(m.get_msgbuf()) for m in expected) == total
    assert s["handler_errors"] == 0
