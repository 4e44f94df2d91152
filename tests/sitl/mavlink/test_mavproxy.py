"""A real client: MAVProxy connects to `pilescan-sitl serve`, loads the exported plan, arms,
switches to AUTO, and the simulated vehicle flies the whole mission and lands."""

import queue
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from pymavlink import mavutil

MAVPROXY = shutil.which("mavproxy.py") or str(Path(sys.executable).parent / "mavproxy.py")
pytestmark = pytest.mark.skipif(not Path(MAVPROXY).exists(), reason="MAVProxy is not installed (pip install MAVProxy)")


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


class Console:
    """MAVProxy's console on pipes: send commands, wait for what it prints."""

    def __init__(self, proc: subprocess.Popen):
        self.proc, self.lines, self.seen = proc, queue.Queue(), []
        threading.Thread(target=lambda: [self.lines.put(x) for x in proc.stdout], daemon=True).start()

    def send(self, command: str) -> None:
        self.proc.stdin.write(command + "\n")
        self.proc.stdin.flush()

    def wait_for(self, text: str, timeout_s: float) -> bool:
        end = time.monotonic() + timeout_s
        if any(text in x for x in self.seen):
            return True
        while time.monotonic() < end:
            try:
                line = self.lines.get(timeout=0.1)
            except queue.Empty:
                continue
            self.seen.append(line)
            if text in line:
                return True
        return False


def test_that_mavproxy_flies_the_exported_plan(tmp_path):
    port = free_udp_port()
    out = tmp_path / "serve"
    # Bounded by itself: 600 simulated seconds at 25x is 24 s of wall time at most.
    srv = subprocess.Popen([sys.executable, "-m", "sitl.cli", "serve", "--mavlink", f"udp:127.0.0.1:{port}",
                            "--speedup", "25", "--duration", "600", "--p-traj", "30", "--out", str(out)],
                           stderr=subprocess.PIPE, text=True)
    mp = subprocess.Popen([MAVPROXY, f"--master=udpout:127.0.0.1:{port}", "--nowait", "--logfile",
                           str(tmp_path / "mavproxy.tlog")], cwd=tmp_path, stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    con = Console(mp)
    try:
        assert con.wait_for("online system 1", 30), "MAVProxy never saw the vehicle"
        con.send(f"wp load {out / 'mission.waypoints'}")
        assert con.wait_for("ACCEPTED", 20), "mission upload not accepted"
        con.send("arm throttle")
        assert con.wait_for("ARMED", 10)
        con.send("mode auto")
        assert con.wait_for("mission complete", 30), "mission did not complete"
        assert con.wait_for("landed and disarmed", 15)
    finally:
        for proc in (mp, srv):
            proc.terminate()
        for proc in (mp, srv):
            try:
                proc.wait(timeout=5)
            except subprocess.TimeoutExpired:  # MAVProxy's module threads can ignore SIGTERM
                proc.kill()
                proc.wait(timeout=5)
    reached = set()
    log = mavutil.mavlink_connection(str(out / "telemetry.tlog"))
    while (m := log.recv_match(type="MISSION_ITEM_REACHED")) is not None:
        reached.add(m.seq)
    # The plan: 0 home, 1 speed, 2 take-off, 3-6 the loop, 7 land.
    assert reached >= set(range(1, 8))
