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
                            "--speedup", "25", "--duration", "600", "--p-traj", "30", "--storage", "30x20x10",
                            "--altitude", "8", "--out", str(out)],
                           stderr=subprocess.PIPE, text=True)
    mp = subprocess.Popen([MAVPROXY, f"--master=udpout:127.0.0.1:{port}", "--nowait", "--logfile",
                           str(tmp_path / "mavproxy.tlog")], cwd=tmp_path, stdin=subprocess.PIPE,
                          stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    con = Console(mp)
    try:
        assert con.wait_for("online system 1", 30), "MAVProxy never saw the vehicle"
        assert con.wait_for(" parameters to ", 30), "MAVProxy never got the parameters"  # "Saved N parameters to"
        con.send(f"wp load {out / 'mission.waypoints'}")
        assert con.wait_for("ACCEPTED", 20), "mission upload not accepted"
        con.send("arm throttle")
        assert con.wait_for("ARMED", 10)
        con.send("mode auto")
        assert con.wait_for("mission complete", 30), "mission did not complete"
        assert con.wait_for("landed and disarmed", 15)
        assert not any("fence breach" in line for line in con.seen)  # SYS_STATUS says the fence is fine
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
    ftp_requests, unanswered, param_list = _ftp_and_param_exchange(tmp_path / "mavproxy.tlog")
    assert ftp_requests >= 1 and not unanswered  # every FTP request refused at once...
    assert param_list  # ...so MAVProxy fell back to the classic parameter protocol


IN_FLIGHT_S = 2.0
"""A request MAVProxy sent this close to the end of its log may still have been in flight when it was stopped."""


def _ftp_and_param_exchange(tlog: Path) -> tuple[int, list[tuple[int, int]], bool]:
    """FTP requests MAVProxy sent, those the vehicle never NAKed (by session and sequence number; a request
    still in flight when MAVProxy was stopped is not counted), and whether a PARAM_REQUEST_LIST followed a NAK."""
    log = mavutil.mavlink_connection(str(tlog))
    requests: dict[tuple[int, int], float] = {}
    answered: set[tuple[int, int]] = set()
    param_list = False
    t_end = 0.0
    while (m := log.recv_match()) is not None:
        t_end = max(t_end, m._timestamp)
        kind = m.get_type()
        if kind == "FILE_TRANSFER_PROTOCOL":
            p = m.payload
            seq, session, opcode = p[0] | p[1] << 8, p[2], p[3]
            if m.get_srcSystem() == 1 and opcode == 129:
                answered.add((session, (seq - 1) & 0xFFFF))
            elif m.get_srcSystem() != 1 and opcode < 128:
                requests.setdefault((session, seq), m._timestamp)
        elif kind == "PARAM_REQUEST_LIST" and answered:
            param_list = True
    unanswered = [k for k, t in requests.items() if k not in answered and t < t_end - IN_FLIGHT_S]
    return len(requests), unanswered, param_list
