"""Faults the simulated bench can inject, and when each one took effect.

A production station meets lost frames, silent nodes, bus errors, refused
EEPROM writes, power glitches and broken sensors; every one of them must end
in a clear station error with the drive safe and nothing stale recorded as a
pass. The simulated bench reproduces them on demand so that this is tested,
not hoped for.

Faults are scheduled in simulated time (SYNCs since the bench powered on), so
a run with a given fault list is as deterministic as one without. Faults that
act on requests rather than on time (SDO timeouts, EEPROM failures) are
*armed* at their time and take effect on the next requests; ``FaultLog``
records when each one actually did something, so a soak run can tell a fault
that hit the unit from one scheduled after the run was over.
"""

from __future__ import annotations

import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass

import can

from drivers.canbus import ControllerProblem, ErrorClass
from station.simsettings import Fault, FaultKind


@dataclass(frozen=True)
class Effect:
    """A fault that did something: at which SYNC, and what."""

    fault: Fault
    sync: int
    what: str


class FaultLog:
    """Which scheduled faults took effect, thread-safe (devices report from bus threads)."""

    def __init__(self, faults: Sequence[Fault]) -> None:
        self.faults = tuple(faults)
        self._lock = threading.Lock()
        self._effects: list[Effect] = []
        self._seen: set[Fault] = set()

    def took_effect(self, fault: Fault, sync: int, what: str) -> None:
        """Note the first time ``fault`` acted (later repeats add nothing)."""
        with self._lock:
            if fault in self._seen:
                return
            self._seen.add(fault)
            self._effects.append(Effect(fault, sync, what))

    @property
    def effects(self) -> tuple[Effect, ...]:
        with self._lock:
            return tuple(self._effects)

    def fired(self, kind: FaultKind) -> bool:
        with self._lock:
            return any(e.fault.kind is kind for e in self._effects)


def due(faults: Iterable[Fault], sync: int, period_s: float) -> list[Fault]:
    """The faults armed exactly at ``sync``."""
    return [f for f in faults if f.at_sync(period_s) == sync]


_ERROR_FRAME_BYTES = 8  # SocketCAN's CAN_ERR_DLC
_PROTOCOL_STUFF_ERROR = 0x04  # data byte 2 of a protocol error: a bit-stuffing violation


def bus_error_frame() -> can.Message:
    """A protocol (stuff) error seen on the bus: the frame was destroyed and is resent.

    Laid out as SocketCAN reports it (linux/can/error.h), which python-can's
    socketcan interface passes through: the class in the identifier.
    """
    data = bytearray(_ERROR_FRAME_BYTES)
    data[2] = _PROTOCOL_STUFF_ERROR
    return can.Message(arbitration_id=ErrorClass.PROTOCOL | ErrorClass.BUS_ERROR, data=data,
                       is_error_frame=True, is_extended_id=False)


def bus_off_frame() -> can.Message:
    """The controller's report that it went bus-off (after passing error-passive)."""
    data = bytearray(_ERROR_FRAME_BYTES)
    data[1] = ControllerProblem.TX_PASSIVE
    return can.Message(arbitration_id=ErrorClass.BUS_OFF | ErrorClass.CONTROLLER, data=data,
                       is_error_frame=True, is_extended_id=False)
