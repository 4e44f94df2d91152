"""tools.rangefinder_share_check: kept flights surveyed again with their autopilot's EKF record in the header."""

import pytest

from firmware_py.core.storage import Storage
from sitl.missions.rectangle import Mission
from sitl.runners.fly import FlyConfig, fly
from tools.rangefinder_share_check import main

MISSION = Mission(storage=Storage(30, 20, 12), p_traj=0.2, altitude_m=8.5, speed_m_s=2.0)


@pytest.fixture(scope="module")
def kept(tmp_path_factory):
    """A pose campaign's folder in miniature: a `flow` flight and its error-free twin (same pile, P_traj, seed)."""
    folder = tmp_path_factory.mktemp("kept")
    for profile in ("none", "flow"):
        fly(FlyConfig(mission=MISSION, plant="ideal", pose_error=profile, seed=3), folder / f"{profile}-1-20-3")
    return folder


def test_that_the_flow_flight_is_surveyed_without_and_with_its_record_against_its_twin(kept, capsys):
    assert main(["--runs", str(kept), "--jobs", "1"]) == 0
    row = [line for line in capsys.readouterr().out.splitlines() if line.startswith(f"| {kept.name} |")]
    assert len(row) == 1
    cells = [c.strip() for c in row[0].strip("|").split("|")]
    assert cells[1] == "1"
    without, with_record = (float(v) for v in cells[2].split(" / "))
    assert with_record < without  # the share taken out brings the flight closer to its twin
