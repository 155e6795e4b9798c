"""The LCM receivers' latency figures: a histogram's bins and percentiles, and the
messages that queued while a run started left out of them."""

import time

import lcm
import numpy as np
import pytest
from pydrake.systems.analysis import Simulator

from maglev_haptics.hardware.link.lcm_messages import markers_t
from maglev_haptics.systems.station_messages import (
    LATENCY_BINS, LATENCY_BINS_PER_DECADE, LATENCY_LOW_S, US_PER_S, MessageReceiver,
    ReceivedChannel, latency_bin, latency_percentile_s, markers_from_message, markers_message,
    receiver_counts, receiver_step)

BIN_RATIO = 10.0 ** (1.0 / LATENCY_BINS_PER_DECADE)  # a bin's upper edge over its lower
NEVER = np.array([-1.0, -np.inf, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])


def upper_edge_s(k: int) -> float:
    return LATENCY_LOW_S * 10.0 ** (k / LATENCY_BINS_PER_DECADE)


def test_latency_bins_are_log_spaced_from_10_us_to_10_s():
    assert [latency_bin(s) for s in (-0.5, 0.0, 1e-6, LATENCY_LOW_S)] == [0, 0, 0, 0]
    assert latency_bin(10.0) == LATENCY_BINS - 2 and latency_bin(10.5) == LATENCY_BINS - 1
    assert latency_bin(1e6) == LATENCY_BINS - 1
    for latency_s in np.geomspace(1.1e-5, 9.9, 997):
        k = latency_bin(latency_s)
        assert upper_edge_s(k) / BIN_RATIO * (1 - 1e-12) < latency_s <= upper_edge_s(k) * (
            1 + 1e-12)
    latencies = np.sort(np.random.default_rng(3).uniform(0.0, 12.0, 500))
    assert np.all(np.diff([latency_bin(s) for s in latencies]) >= 0)


@pytest.mark.parametrize("percent", [1, 50, 90, 99, 100])
def test_a_percentile_from_the_histogram_is_the_true_one_within_a_bin(percent):
    """Nearest rank (the smallest latency that ``percent`` % of them do not exceed),
    read as its bin's upper edge: at most one bin (12%) over, never over the largest."""
    rng = np.random.default_rng(percent)
    latencies = rng.lognormal(np.log(3e-4), 1.0, 2000)
    histogram = np.zeros(LATENCY_BINS)
    for latency_s in latencies:
        histogram[latency_bin(latency_s)] += 1
    true = np.percentile(latencies, percent, method="inverted_cdf")
    read = latency_percentile_s(histogram, percent, latencies.max())
    assert true * (1 - 1e-12) <= read <= true * BIN_RATIO * (1 + 1e-12)
    if percent == 100:
        assert read == latencies.max()


def test_percentiles_see_through_a_few_late_messages_that_move_the_mean():
    """990 messages at 0.3 ms and 10 at 0.6 s: the mean says 6.3 ms, p50 and p99 0.3 ms."""
    histogram = np.zeros(LATENCY_BINS)
    state = NEVER.tolist()
    for sequence, latency_s in enumerate([3e-4] * 990 + [0.6] * 10):
        state = receiver_step(state, sequence, sequence * 1e-3, latency_s)
        histogram[latency_bin(latency_s)] += 1
    counts = receiver_counts(state, histogram)
    assert counts["latency_ms_mean"] == pytest.approx(6.297)
    assert counts["latency_ms_max"] == pytest.approx(600.0)
    for name in ("latency_ms_p50", "latency_ms_p99"):
        assert 0.3 <= counts[name] <= 0.3 * BIN_RATIO
    assert latency_percentile_s(np.zeros(LATENCY_BINS), 50, 0.0) is None
    # Past the histogram's top (10 s): the largest, not the top's edge.
    histogram[LATENCY_BINS - 1] += 20
    assert latency_percentile_s(histogram, 99, 42.0) == 42.0


def test_a_message_read_at_the_start_is_received_and_its_latency_left_out():
    state = receiver_step(NEVER.tolist(), 1, 0.0, 0.8, at_start=True)
    counts = receiver_counts(state, np.zeros(LATENCY_BINS))
    assert (counts["messages_received"], counts["messages_at_start"]) == (1, 1)
    assert counts["latency_ms_mean"] is None and counts["latency_ms_p50"] is None
    assert counts["latency_ms_max"] is None
    histogram = np.zeros(LATENCY_BINS)
    state = receiver_step(state, 3, 0.001, 0.0004)
    histogram[latency_bin(0.0004)] += 1
    counts = receiver_counts(state, histogram)
    assert (counts["messages_received"], counts["messages_lost"],
            counts["messages_at_start"]) == (2, 1, 1)
    assert counts["latency_ms_mean"] == pytest.approx(0.4)
    assert counts["latency_ms_max"] == pytest.approx(0.4)
    assert counts["longest_gap_ms"] == pytest.approx(1.0)


def sent_ago(bus, sequence: int, age_s: float) -> None:
    """A marker message on M stamped as sent ``age_s`` (s) ago on the wall clock."""
    message = markers_message(sequence, 0.0, 0.0, np.zeros(3))
    message.sent_wall_utime = time.time_ns() // 1000 - round(age_s * US_PER_S)
    bus.publish("M", message.encode())


def test_what_queued_while_the_run_started_is_left_out_of_the_latency():
    """What a receiver reads at its initialization (queued while the diagram was built)
    and at its first tick (queued while the run was set up, up to a second with
    Meshcat) carries the start's wait, not the link's: received, counted at the start,
    left out of the latency; from the second tick on every message counts."""
    bus = lcm.LCM("memq://")
    receiver = MessageReceiver(lcm=bus, period_s=0.001, channels=[ReceivedChannel(
        port="markers", channel="M", message_type=markers_t, size=3,
        decode=lambda message, _: markers_from_message(message, 1),
        initial_value=np.zeros(3))])
    simulator = Simulator(receiver)
    for sequence in (1, 2):
        sent_ago(bus, sequence, 0.9)  # while the diagram was built: only the newest is read
    simulator.Initialize()
    for sequence in (3, 4, 5):
        sent_ago(bus, sequence, 0.6)  # while the run was set up
    simulator.AdvanceTo(0.0005)  # the first tick, at 0
    for sequence, t_s in ((6, 0.001), (7, 0.002)):
        sent_ago(bus, sequence, 0.0)
        simulator.AdvanceTo(t_s + 0.0005)
    counts = receiver.counts(receiver.GetMyContextFromRoot(simulator.get_context()), "markers")
    assert (counts["messages_received"], counts["messages_at_start"]) == (6, 4)
    assert counts["messages_lost"] == 0  # the count starts at the first message read
    assert 0.0 <= counts["latency_ms_p50"] <= counts["latency_ms_max"] < 100.0
    assert counts["latency_ms_mean"] < 100.0
