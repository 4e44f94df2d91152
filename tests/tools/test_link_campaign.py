"""The link campaign's parts: its floods are what they claim, its section rewrite keeps the rest of
the file, and one small flood runs through it end to end (no timing thresholds asserted)."""

import random

import pytest

from sitl.mavlink.datagrams import DatagramParser, Drop
from tools.doc_sections import write_section
from tools.link_campaign import (
    END,
    FLOOD_KINDS,
    SECTION,
    START,
    CampaignConfig,
    Measured,
    Scenario,
    flood_datagram,
    make_key_file,
    render,
    run_scenario,
    scenarios,
)


@pytest.mark.parametrize("kind, drop", [("truncated", Drop.TRUNCATED), ("bad_crc", Drop.BAD_FRAME)])
def test_that_the_malformed_floods_are_dropped_for_the_reason_they_are_named_after(kind, drop):
    parser = DatagramParser()
    rng = random.Random(1)
    for k in range(20):
        assert parser.parse(flood_datagram(kind, 3, k, rng)) == []
    assert parser.drops == {drop: 20}


@pytest.mark.parametrize("kind, mtype", [("command", "COMMAND_LONG"), ("param_nan", "PARAM_SET"),
                                         ("mission_count", "MISSION_COUNT")])
def test_that_the_absurd_request_floods_are_valid_frames(kind, mtype):
    rng = random.Random(1)
    msgs = [m for k in range(20) for m in DatagramParser().parse(flood_datagram(kind, 3, k, rng))]
    assert len(msgs) == 20 and {m.get_type() for m in msgs} == {mtype}
    assert {m.get_srcSystem() for m in msgs} == {103}


def test_that_every_flood_kind_has_a_scenario():
    assert {s.kind for s in scenarios()} == {None, *FLOOD_KINDS}


def test_that_write_section_replaces_only_its_own_section(tmp_path):
    doc = tmp_path / "reliability.md"
    doc.write_text("# Reliability\n\nkept before\n")
    write_section(doc, SECTION, "first\n")
    doc.write_text(doc.read_text() + "\nkept after\n")
    write_section(doc, SECTION, "second\n")
    text = doc.read_text()
    assert text.count(START) == 1 and "second" in text and "first" not in text
    assert text.startswith("# Reliability\n\nkept before\n") and text.rstrip().endswith("kept after")


def test_that_a_small_flood_runs_through_the_campaign(tmp_path):
    key, key_file = make_key_file(tmp_path)
    cfg = CampaignConfig(flood_s=2.0, rate_hz=300.0, warmup_s=0.5, mission_items=5)
    res = run_scenario(Scenario("truncated x10", "truncated", 10), cfg, tmp_path, key, key_file)
    assert res.error == ""
    assert res.flood_sent == 600 and res.server_dropped > 0  # the server saw and dropped the flood
    assert res.unsolicited == {}  # nothing of the flooders' reached the ground station
    assert res.latencies_s and res.rss_peak_mb > 0
    section = render([res, Measured(Scenario("broken", None), error="no HEARTBEAT")], cfg, 3.0)
    assert section.startswith("## Link campaign") and START not in section and END not in section
    assert "| truncated x10 | 600 |" in section and "error: no HEARTBEAT" in section
