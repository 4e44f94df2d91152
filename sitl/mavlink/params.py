"""The parameter micro-service: the vehicle's `PS_*` and any extra provider's, listed, read and set alike.

Sorted by name, as ArduPilot lists them, so an index means the same parameter to every client;
`pilescan-sitl serve` serves its `SIM_PS_*` fault parameters as the extra ones (`sitl.faults.params`).
Reads are answered to the asker; a parameter that changed is announced to every client (as
ArduPilot does, so every ground station shows the new value); a refused PARAM_SET (unknown name,
NaN, out of range) is answered to the asker alone: its read-back and a STATUSTEXT saying why.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, Protocol

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from sitl.mavlink.outbox import Outbox
from sitl.vehicle.api import Vehicle


class ParamProvider(Protocol):
    """Parameters served beside the vehicle's own (e.g. `sitl.faults.params.FaultParams`: the SIM_PS_*)."""

    def names(self) -> list[str]:
        """The names now available (a vehicle parameter of the same name wins)."""

    def get(self, name: str) -> float: ...

    def set(self, name: str, value: float) -> float | None:
        """Set at once; KeyError for an unknown name, ValueError for a bad value (nothing changed).

        Returns the value the PARAM_VALUE acknowledging it carries, or None for get(name): an action
        parameter acknowledges what it did (a ground station such as MAVProxy re-sends a set until the
        value it sent comes back), then reads back its state.
        """


class Params:
    """PARAM_REQUEST_LIST / _READ and PARAM_SET, answered with PARAM_VALUE (REAL32) through `out`."""

    def __init__(self, vehicle: Vehicle, extra: ParamProvider | None, mav: Any, out: Outbox) -> None:
        self.vehicle, self.extra = vehicle, extra
        self._mav, self._out = mav, out
        self.handlers: dict[str, Callable[[Any], None]] = {
            "PARAM_REQUEST_LIST": self._on_param_request_list, "PARAM_REQUEST_READ": self._on_param_request_read,
            "PARAM_SET": self._on_param_set,
        }
        """Message type -> handler, for the messages this service answers."""

    def names(self) -> list[str]:
        """The vehicle's parameters and the extra ones, sorted by name as ArduPilot does."""
        extra = self.extra.names() if self.extra is not None else []
        return sorted(set(self.vehicle.params).union(extra))

    def value(self, name: str) -> float:
        if name in self.vehicle.params:
            return self.vehicle.params[name]
        return self.extra.get(name)

    def set(self, name: str, value: float) -> float | None:
        """Set a vehicle or an extra parameter; the value to acknowledge with (None: read it back)."""
        if name in self.vehicle.params or self.extra is None or name not in self.extra.names():
            self.vehicle.set_param(name, value)  # KeyError for a name nobody has
            return None
        return self.extra.set(name, value)

    def _send_param(self, name: str, value: float | None = None, to_all: bool = False) -> None:
        names = self.names()
        value = self.value(name) if value is None else value
        send = self._out.broadcast if to_all else self._out.reply
        send(self._mav.param_value_encode(name.encode("ascii", "replace")[:16], value,
                                                mavlink.MAV_PARAM_TYPE_REAL32, len(names), names.index(name)))

    def _on_param_request_list(self, msg: Any) -> None:
        for name in self.names():
            self._send_param(name)

    def _on_param_request_read(self, msg: Any) -> None:
        names = self.names()
        if msg.param_index >= 0:
            if msg.param_index < len(names):
                self._send_param(names[msg.param_index])
        elif msg.param_id in names:
            self._send_param(msg.param_id)

    def _on_param_set(self, msg: Any) -> None:
        name = msg.param_id
        try:
            ack = self.set(name, msg.param_value)
        except KeyError:
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"unknown parameter {name}")
            return
        except ValueError as exc:
            self._out.say(mavlink.MAV_SEVERITY_WARNING, f"param {name} not set: {exc}")
            self._send_param(name)  # the value kept, to the asker alone
            return
        self._send_param(name, ack, to_all=True)
