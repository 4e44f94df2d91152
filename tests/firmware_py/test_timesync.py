import math
import random
import statistics

import pytest

from firmware_py.timesync import TimesyncConfig, TimesyncEstimator

MS = 1_000_000
S = 1_000_000_000
C0 = 5_000 * S  # companion monotonic time at the start of a test


def exchange(est: TimesyncEstimator, now_ns: int, offset_ns: int, up_ns: int, down_ns: int,
             drift: float = 0.0) -> bool:
    """One TIMESYNC round trip: request at companion now_ns, reply after up + down (autopilot = companion + offset)."""
    tc1, ts1 = est.request(now_ns)
    assert tc1 == 0 and ts1 == now_ns
    t_handle = now_ns + up_ns
    autopilot = t_handle + offset_ns + round(drift * (t_handle - C0))
    return est.on_reply(autopilot, ts1, now_ns + up_ns + down_ns)


def converge(est: TimesyncEstimator, offset_ns: int, t0: int = C0, n: int | None = None, period_ns: int = 100 * MS,
             rtt_ns: int = 10 * MS) -> int:
    """n symmetric round trips (exact samples); returns the companion time after them."""
    n = est.config.converge_samples if n is None else n
    t = t0
    for _ in range(n):
        assert exchange(est, t, offset_ns, rtt_ns // 2, rtt_ns // 2)
        t += period_ns
    return t


def test_offset_is_autopilot_minus_companion_and_maps_both_ways():
    est = TimesyncEstimator()
    offset = -4_321 * S + 123_457  # autopilot booted long after the companion
    assert exchange(est, C0, offset, 3 * MS, 3 * MS)
    assert est.offset_ns == offset
    assert est.last_rtt_ns == 6 * MS
    assert est.to_companion_ns(C0 + offset) == C0
    assert est.to_autopilot_ns(C0) == C0 + offset


def test_offset_matches_the_mavros_formula_with_its_sign():
    est = TimesyncEstimator()
    tc1, ts1, now = 2_000 * MS, 9_000 * MS, 9_010 * MS
    est.request(ts1)
    est.on_reply(tc1, ts1, now)
    assert est.offset_ns == (2 * tc1 - (ts1 + now)) // 2


def test_large_clock_values_keep_nanosecond_precision():
    est = TimesyncEstimator()
    companion = 1_700_000_000 * S + 1  # an epoch-based clock: 1.7e18 ns, beyond a float's ns resolution
    offset = -companion + 37 * S + 3
    for k in range(30):
        assert exchange(est, companion + k * S, offset, 2 * MS, 2 * MS)
    assert est.offset_ns == offset


def test_a_reply_to_a_request_we_did_not_send_is_ignored_and_so_is_a_duplicate():
    est = TimesyncEstimator()
    assert not est.on_reply(1_000, C0, C0 + 10 * MS)  # never requested
    _, ts1 = est.request(C0)
    assert est.on_reply(123 * S, ts1, C0 + 10 * MS)
    assert not est.on_reply(999 * S, ts1, C0 + 12 * MS)  # the same request answered twice
    assert est.stats["unmatched"] == 2 and est.stats["samples"] == 1


def test_a_timesync_request_from_the_autopilot_is_not_a_reply():
    est = TimesyncEstimator()
    _, ts1 = est.request(C0)
    assert not est.on_reply(0, ts1, C0 + 5 * MS)
    assert not est.has_estimate


def test_a_negative_round_trip_is_rejected():
    est = TimesyncEstimator()
    _, ts1 = est.request(C0)
    assert not est.on_reply(7 * S, ts1, C0 - 1 * MS)
    assert est.stats["invalid"] == 1 and est.stats["rejected"] == 1
    assert est.offset_ns is None


def test_mapping_before_any_sample_raises_instead_of_guessing():
    est = TimesyncEstimator()
    with pytest.raises(RuntimeError, match="no TIMESYNC estimate"):
        est.to_companion_ns(0)
    with pytest.raises(RuntimeError, match="no TIMESYNC estimate"):
        est.to_autopilot_ns(0)


def test_first_samples_are_a_running_mean():
    est = TimesyncEstimator()
    offset = 50 * S
    asym = [4, -2, 6, 0, -8, 2, 3]  # ms: sample error = (up - down) / 2
    for k, a in enumerate(asym):
        exchange(est, C0 + k * S, offset, (10 + a) * MS, (10 - a) * MS)
    assert est.offset_ns == offset + round(statistics.mean(asym) * MS)


def test_after_the_running_mean_the_gain_is_set_by_the_time_constant():
    cfg = TimesyncConfig(time_constant_s=10.0, converge_samples=5)
    est = TimesyncEstimator(cfg)
    offset = 50 * S
    t = converge(est, offset, n=200, period_ns=1 * S)  # 1 - exp(-1/10) = 0.095 > 1/200: EMA phase
    before = est.offset_ns
    assert exchange(est, t, offset, 14 * MS, 6 * MS)  # a +4 ms sample, received 1.01 s after the previous
    assert est.offset_ns - before == pytest.approx(4 * MS * -math.expm1(-1.01 / 10), abs=2)


def test_converged_only_after_converge_samples_accepted_samples():
    est = TimesyncEstimator(TimesyncConfig(converge_samples=6))
    for k in range(6):
        assert not est.converged
        exchange(est, C0 + k * S, 0, 5 * MS, 5 * MS)
    assert est.converged and est.samples == 6


def test_a_latency_outlier_is_rejected_relative_to_the_running_minimum_rtt():
    est = TimesyncEstimator()  # outlier above 2 x min + 30 ms
    offset = 7 * S
    t = converge(est, offset, rtt_ns=10 * MS)
    assert not exchange(est, t, offset, 195 * MS, 5 * MS)  # 200 ms round trip, 95 ms asymmetric
    assert est.offset_ns == offset
    assert est.stats["rejected_rtt"] == 1
    assert exchange(est, t + S, offset, 25 * MS, 20 * MS)  # slower than usual (45 ms) but no outlier


def test_the_running_minimum_follows_a_link_that_got_slower():
    cfg = TimesyncConfig(rtt_window=8)
    est = TimesyncEstimator(cfg)
    offset = 7 * S
    t = converge(est, offset, rtt_ns=5 * MS)
    accepted = [exchange(est, t + k * S, offset, 50 * MS, 50 * MS) for k in range(12)]
    assert accepted[:7] == [False] * 7  # 100 ms vs 2 x 5 + 30: outliers while a 5 ms reply is in the window
    assert all(accepted[8:])  # the window now holds only slow replies: they are the new normal


def test_a_deviation_jitter_cannot_explain_resets_at_once_and_restarts_from_that_sample():
    est = TimesyncEstimator()
    t = converge(est, 7 * S)
    assert est.converged
    new_offset = 7 * S - 3_600 * S  # the companion clock jumped forward by an hour
    assert exchange(est, t, new_offset, 5 * MS, 5 * MS)
    assert est.stats["resets"] == 1 and "clock jump" in est.last_reset_reason
    assert est.offset_ns == new_offset
    assert not est.converged and est.samples == 1


def test_a_small_jump_within_the_jitter_bound_needs_jump_confirm_samples_agreeing_samples():
    est = TimesyncEstimator()
    t = converge(est, 7 * S, rtt_ns=40 * MS)
    shifted = 7 * S + 15 * MS  # > 10 ms, but below 10 ms + rtt / 2 = 30 ms: could be one-sided delay
    n = est.config.jump_confirm_samples
    for k in range(n - 1):
        assert not exchange(est, t + k * S, shifted, 20 * MS, 20 * MS)
    assert est.stats["resets"] == 0 and est.offset_ns == 7 * S
    assert exchange(est, t + n * S, shifted, 20 * MS, 20 * MS)
    assert est.stats["resets"] == 1 and est.offset_ns == shifted


def test_high_deviations_of_alternating_sign_are_jitter_not_a_jump():
    est = TimesyncEstimator()
    t = converge(est, 7 * S, rtt_ns=40 * MS)
    for k in range(20):
        a = 12 if k % 4 < 2 else -12  # ms of one-sided delay, two each way in turn
        exchange(est, t + k * S, 7 * S, (20 + a) * MS, (20 - a) * MS)
    assert est.stats["resets"] == 0
    assert est.stats["rejected_deviation"] == 20


def test_replies_to_requests_sent_before_a_reset_are_ignored():
    est = TimesyncEstimator()
    t = converge(est, 7 * S)
    _, old_ts1 = est.request(t)
    est.reset("test")
    assert not est.on_reply(7 * S + t, old_ts1, t + 10 * MS)
    assert est.offset_ns is None and est.stats["unmatched"] == 1


def test_time_boot_ms_going_back_is_a_reboot_but_reordering_is_not():
    est = TimesyncEstimator()
    t = converge(est, 7 * S)
    assert not est.on_boot_time(60_000, t)
    assert not est.on_boot_time(59_700, t)  # a late UDP packet: 300 ms back
    assert est.converged
    assert est.on_boot_time(1_500, t)  # rebooted
    assert est.stats["resets"] == 1 and "reboot" in est.last_reset_reason
    assert not est.converged
    assert not est.on_boot_time(1_520, t + 20 * MS)  # the new boot's clock is the reference now


def test_an_autopilot_time_mapping_into_the_future_means_the_companion_clock_jumped_back():
    est = TimesyncEstimator()
    offset = 7 * S
    t = converge(est, offset)
    boot_now_ms = (t + offset) // MS
    assert not est.on_boot_time(boot_now_ms - 20, t)  # 20 ms old: normal latency
    t_jumped = t - 3_600 * S  # the companion clock went back an hour
    assert est.on_boot_time(boot_now_ms + 10, t_jumped)
    assert "future" in est.last_reset_reason


def test_seeded_random_latency_of_5_to_30_ms_averages_to_below_a_millisecond():
    rng = random.Random(42)
    est = TimesyncEstimator()
    offset = -123_456_789_012
    errors = []
    for k in range(3000):  # 10 Hz for 300 s
        t = C0 + k * 100 * MS
        exchange(est, t, offset, rng.randint(5 * MS, 30 * MS), rng.randint(5 * MS, 30 * MS))
        if est.converged:
            errors.append(abs(est.offset_ns - offset))
    assert len(errors) > 2900
    assert statistics.median(errors) < 1 * MS
    assert est.stats["resets"] == 0


def test_seeded_latency_outliers_are_rejected_and_do_not_reset_the_filter():
    rng = random.Random(7)
    est = TimesyncEstimator()
    offset = 3 * S
    errors = []
    for k in range(3000):
        t = C0 + k * 100 * MS
        up, down = rng.randint(5 * MS, 30 * MS), rng.randint(5 * MS, 30 * MS)
        if rng.random() < 0.1:
            up += rng.randint(100 * MS, 400 * MS)  # a one-sided stall: up to 200 ms of offset error
        exchange(est, t, offset, up, down)
        if est.converged:
            errors.append(abs(est.offset_ns - offset))
    assert est.stats["rejected_rtt"] > 200
    assert est.stats["resets"] == 0
    assert statistics.median(errors) < 1 * MS


def test_clock_drift_lags_the_estimate_by_drift_times_the_time_constant():
    est = TimesyncEstimator(TimesyncConfig(time_constant_s=10.0))
    drift = 50e-6  # the autopilot's crystal runs 50 ppm fast
    t = C0
    for _ in range(600):  # 1 Hz, 10 minutes, quiet link
        exchange(est, t, 0, 2 * MS, 2 * MS, drift=drift)
        t += S
    true_offset = round(drift * (t - S + 2 * MS - C0))
    lag = true_offset - est.offset_ns
    assert lag == pytest.approx(drift * 10.0 * S, rel=0.1)  # 0.5 ms: why the time constant is 10 s


@pytest.mark.parametrize("field,value", [
    ("converge_samples", 0), ("rtt_window", 0), ("jump_confirm_samples", 0), ("pending_requests", 0),
    ("rtt_reject_slack_ns", -1), ("jump_ns", -1), ("reboot_tolerance_ms", -5), ("time_constant_s", 0.0),
    ("time_constant_s", math.nan), ("rtt_reject_factor", 0.5), ("rtt_reject_factor", math.inf),
])
def test_bad_configuration_is_refused_naming_the_value(field, value):
    with pytest.raises(ValueError, match=field):
        TimesyncConfig(**{field: value})
