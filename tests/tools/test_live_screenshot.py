"""The live page in headless Chromium while a networked SITL flight streams to `listen --web` (four processes
on real sockets, in real time, about 30 s): the page's record count grows as the vehicle flies, it shows the
volume with its 90 % interval (the report's computation on the very records `listen` logged), says when the
stream stops, and its canvas is drawn (read back from a screenshot, not from the page's own word).

No timing assertions: every wait is on a condition the page must reach, with a generous deadline. Skipped
only where no Chromium is installed; .ci/run installs Debian's chromium, so CI runs it.
"""

from __future__ import annotations

import re

import matplotlib.image as mpimg
import numpy as np
import pytest

from firmware_py.core.samplelog import read_samplelog
from ground.listen import load_header
from ground.live_state import LIVE_REPORT_OPTIONS, LiveGeometry
from ground.report import summarise, survey_from_samples
from ground.surface import grid_volume
from tools.live_screenshot import Chromium, LivePage, find_chromium, live_flight

pytestmark = [pytest.mark.skipif(find_chromium() is None,
                                 reason="no Chromium installed (apt-get install chromium; .ci/run installs it)"),
              pytest.mark.long]  # scheduled first (tests/conftest.py)

FLIGHT_S = 8.0
"""Seconds flown after AUTO: enough for the sweeps to give a surface (tests/tools/test_fly_networked.py)."""
TRACK_RGB = np.array([0xE8, 0x59, 0x0C]) / 255.0


def test_that_the_live_page_shows_a_networked_flight_as_it_is_flown(tmp_path):
    with Chromium() as browser, live_flight(tmp_path, FLIGHT_S) as (listen, flight, outcome):
        page = LivePage(browser, listen.url)
        first = page.wait_for(lambda v: v.records > 0, 90.0, "a first record")
        grown = page.wait_for(lambda v: v.records > first.records and v.polls > first.polls, 60.0,
                              "a record count growing as the page polls")
        assert grown.status == "receiving" and re.fullmatch(r"[\d,]+", grown.records_text)
        flight.join(180.0)
        assert not flight.is_alive() and "error" not in outcome, outcome.get("error")
        assert outcome["run"].payload_exit == 0
        # The stream has stopped: the page says so, and its last volume covers every record received.
        final = page.wait_for(lambda v: "no data for" in v.status and v.volume is not None and v.interval is not None
                              and v.volume_records == v.records, 60.0, "the final volume and the stopped stream")
        shot = browser.screenshot(tmp_path / "live.png")
    code, summary = listen.stop()
    assert code == 0 and f"live page     {listen.url}" in summary

    lo, hi = final.interval
    assert 0 <= lo <= final.volume <= hi and lo < hi  # 0: the floor, which a short flight's unseen area may reach
    assert re.fullmatch(r"[\d,]+\.\d m³", final.volume_text) and re.fullmatch(r"[\d,]+\.\d – [\d,]+\.\d m³",
                                                                                final.interval_text)
    # What the page showed is the report's computation on the records listen logged, no more, no less.
    log = read_samplelog(tmp_path / "live.pslog")
    assert len(log.samples) == final.records
    geo = LiveGeometry.from_header(load_header(tmp_path / "header.json"), "header")
    survey = survey_from_samples(log.samples, log.header, geo.storage, geo.frame, np.asarray(geo.lever_arm_body_m),
                                 LIVE_REPORT_OPTIONS)
    assert grid_volume(survey.heights, survey.grid) == pytest.approx(final.volume, rel=1e-9)
    rep = summarise(survey, log, LIVE_REPORT_OPTIONS, None)
    assert rep["volume_interval_m3"] == pytest.approx(list(final.interval), rel=1e-9)

    # The canvas, as the screenshot has it: cells in the height colours, the hatched unseen floor, the track.
    assert final.cells_points > 0 and final.cells_unseen > 0 and final.track_points > 10
    img = mpimg.imread(shot)[..., :3]
    x, y, w, h = final.canvas
    canvas = img[y:y + h, x:x + w].reshape(-1, 3)
    white = np.all(canvas > 0.97, axis=1)
    grey = np.ptp(canvas, axis=1) < 0.03
    coloured = ~white & ~grey
    assert coloured.mean() > 0.01  # the height colours and the track
    assert grey[~white].mean() > 0.2  # the hatched unseen floor and the outline
    assert np.any(np.all(np.abs(canvas - TRACK_RGB) < 0.06, axis=1))  # the track's orange
