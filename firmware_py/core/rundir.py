"""The names of the files in a run directory: what the SITL writes and the ground station reads.

A run directory is one survey flight: the payload's sample log, the truth the SITL knows (absent
for a real flight), the stockpile mesh the LiDAR saw, the vehicle's MAVLink telemetry log and the
mission plan.
"""

from __future__ import annotations

SAMPLES_FILE = "samples.pslog"
"""The payload's sample log (`firmware_py.core.samplelog`)."""
TRUTH_FILE = "truth.json"
"""What the SITL knows and a real flight does not: true volume, building, mission, seeds, energy."""
PILE_FILE = "pile.stl"
"""The stockpile mesh the emulated LiDAR ray traced, in the storage frame W."""
TLOG_FILE = "telemetry.tlog"
"""Every MAVLink frame the vehicle sent and received (pymavlink's `mavlogdump.py` reads it)."""
PLAN_FILE = "mission.waypoints"
"""The mission as QGC WPL 110, loadable by any ground station."""
