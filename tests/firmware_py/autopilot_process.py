"""The SITL autopilot for the payload's tests, in a process of its own, as a real autopilot is another machine.

Run in the test's own process (a thread beside the payload's loop), the autopilot shared the interpreter with the
payload under test, and on a machine loaded several times over it starved: fewer than half the samples got a fresh pose
and a sound preflight failed its pose check (seen once in CI). Here it runs as `python -m
tests.firmware_py.autopilot_process`: the SITL's kinematic vehicle served over real UDP by `run_realtime`, behind a
transport that records what the payload sends. The test talks to it over the child's stdin and stdout, one JSON line a
request and one a reply; every request runs in the server's thread, between two physics steps, so the vehicle is only
ever touched by one thread. When the test's process dies, the child reads the end of its stdin and stops.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

REPO = Path(__file__).resolve().parents[2]
HOME_NED = (3.0, 4.0, 0.0)
"""The vehicle's home in the autopilot's NED frame (m): where it sits on the ground."""
REPLY_TIMEOUT_S = 20.0
"""How long a request waits for the child's answer before the test is told the autopilot is gone."""


class Autopilot:
    """The test's handle on the autopilot process: its UDP url, what the payload sent it, and arm / disarm."""

    def __init__(self, armed: bool = False, params: dict[str, float] | None = None, *, signing_key: bytes | None = None,
                 tlog: Path | None = None) -> None:
        env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
        self._proc = subprocess.Popen([sys.executable, "-m", "tests.firmware_py.autopilot_process"], cwd=REPO,
                                      stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True, bufsize=1, env=env)
        self._lock = threading.Lock()
        self._last: dict[str, Any] | None = None  # what the child said as it closed: asked for after close()
        try:
            hello = self._ask({"armed": armed, "params": params or {}, "tlog": None if tlog is None else str(tlog),
                               "signing_key": None if signing_key is None else signing_key.hex()})
        except BaseException:  # a child that did not start is not left behind
            self._proc.kill()
            self._proc.wait()
            raise
        self.port = int(hello["port"])

    @property
    def url(self) -> str:
        return f"udpout:127.0.0.1:{self.port}"

    def _ask(self, request: dict[str, Any]) -> dict[str, Any]:
        if self._last is not None:
            return self._last
        with self._lock:
            if self._proc.poll() is not None:
                raise RuntimeError(f"the autopilot process ended (exit code {self._proc.returncode})")
            self._proc.stdin.write(json.dumps(request) + "\n")
            self._proc.stdin.flush()
            answer: list[str] = []
            reader = threading.Thread(target=lambda: answer.append(self._proc.stdout.readline()), daemon=True)
            reader.start()
            reader.join(REPLY_TIMEOUT_S)
            if not answer or not answer[0]:
                raise RuntimeError(f"the autopilot process did not answer {request.get('op', 'its start')!r}")
            return json.loads(answer[0])

    def of_type(self, kind: str) -> list[SimpleNamespace]:
        """The messages of this MAVLink type the payload sent, in order, each with its fields as attributes."""
        return [SimpleNamespace(**m) for m in self._ask({"op": "of_type", "kind": kind})["messages"]
                if m["mavpackettype"] == kind]

    def texts(self) -> list[str]:
        """The STATUSTEXTs the payload sent, in order."""
        return [m.text for m in self.of_type("STATUSTEXT")]

    def stats(self) -> dict[str, Any]:
        """The server's counters (`MavlinkVehicleServer.stats`)."""
        return self._ask({"op": "stats"})["stats"]

    def armed(self) -> bool:
        return bool(self._ask({"op": "armed"})["armed"])

    def arm(self) -> None:
        self._ask({"op": "arm"})

    def disarm(self) -> None:
        self._ask({"op": "disarm"})

    def wait_for(self, cond, timeout_s: float = 5.0) -> bool:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            if cond():
                return True
            time.sleep(0.02)
        return cond()

    def close(self) -> None:
        """Stop the autopilot; what it received stays to be asked for."""
        if self._last is not None:
            return
        try:
            self._last = self._ask({"op": "close"})
        except (RuntimeError, OSError, ValueError):
            self._last = {"messages": [], "stats": {}, "armed": False}
        finally:
            try:
                self._proc.stdin.close()
                self._proc.wait(timeout=5.0)
            except subprocess.TimeoutExpired:
                self._proc.kill()
                self._proc.wait()
            self._proc.stdout.close()


# ----- the child ----------------------------------------------------------------------------------------------------

def _serve() -> None:
    import queue

    from firmware_py.hal.mavlink_link import MavlinkFramer
    from firmware_py.hal.signing import SigningConfig
    from sitl.mavlink.server import MavlinkVehicleServer, run_realtime
    from sitl.mavlink.transport import UdpTransport
    from sitl.vehicle.kinematic_vehicle import KinematicVehicle

    class SpyTransport:
        """The server's UDP transport, also parsing what the payload sends and running the test's requests in the
        server's thread."""

        def __init__(self, inner: UdpTransport) -> None:
            self.inner, self.framer, self.received = inner, MavlinkFramer(), []
            self.requests: queue.SimpleQueue = queue.SimpleQueue()

        def send(self, data: bytes) -> None:
            self.inner.send(data)

        def recv(self) -> bytes:
            while not self.requests.empty():
                self.requests.get()()
            data = self.inner.recv()
            if data:
                self.received.extend(self.framer.feed(data))
            return data

        def close(self) -> None:
            self.inner.close()

    replies, sys.stdout = sys.stdout, sys.stderr  # the replies' line is the test's alone: stray prints go to stderr

    def reply(answer: dict[str, Any]) -> None:
        replies.write(json.dumps(answer, default=str) + "\n")
        replies.flush()

    start = json.loads(sys.stdin.readline())
    vehicle = KinematicVehicle(dt_s=0.002, home_ned_m=HOME_NED)
    vehicle.params.update(start["params"])
    if start["armed"]:
        vehicle.arm()
    spy = SpyTransport(UdpTransport("udp:127.0.0.1:0"))
    key = start["signing_key"]
    server = MavlinkVehicleServer(vehicle, spy, tlog_path=start["tlog"],
                                  signing=None if key is None else SigningConfig(bytes.fromhex(key)))
    stop = threading.Event()

    def answer(request: dict[str, Any]) -> None:
        op = request["op"]
        if op == "of_type":
            reply({"messages": [m.to_dict() for m in spy.received if m.get_type() == request["kind"]]})
        elif op == "stats":
            reply({"stats": server.stats})
        elif op == "armed":
            reply({"armed": vehicle.state().armed})
        elif op == "arm":
            vehicle.arm()
            reply({})
        elif op == "disarm":
            vehicle.disarm()
            reply({})
        else:
            reply({"error": f"unknown request {op!r}"})

    def listen() -> None:
        for line in sys.stdin:
            request = json.loads(line)
            if request.get("op") == "close":
                break
            spy.requests.put(lambda request=request: answer(request))
        stop.set()  # asked to close, or the test's process is gone

    threading.Thread(target=listen, daemon=True).start()
    reply({"port": spy.inner.local_address[1]})
    try:
        run_realtime(server, vehicle, stop_event=stop)
    finally:
        server.close()
        spy.close()
        # all it received, its counters and state: the test may ask after closing it
        reply({"messages": [m.to_dict() for m in spy.received], "stats": server.stats, "armed": vehicle.state().armed})


if __name__ == "__main__":
    _serve()
