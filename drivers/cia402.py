"""The CiA 402 power state machine as the station walks it, whatever the transport.

A CANopen drive and a Modbus drive share the controlword and statusword
(ICD.md §4 maps them "as 0x6040/0x6041"), so the walk to operation enabled
and the wait for de-energised are written once; each driver supplies how it
reads the statusword and writes the controlword.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from enum import IntEnum

from drivers.base import DriveState, decode_statusword
from station.errors import DeviceStateError


class Controlword(IntEnum):
    """CiA 402 device control commands (bits 0-3 and 7 of 0x6040)."""

    DISABLE_VOLTAGE = 0x0000
    SHUTDOWN = 0x0006
    SWITCH_ON = 0x0007
    ENABLE_OPERATION = 0x000F
    FAULT_RESET = 0x0080


# The path from any stable state towards operation enabled: command, expected state.
ENABLE_STEPS: dict[DriveState, tuple[Controlword, DriveState]] = {
    DriveState.FAULT: (Controlword.FAULT_RESET, DriveState.SWITCH_ON_DISABLED),
    DriveState.QUICK_STOP_ACTIVE: (Controlword.DISABLE_VOLTAGE, DriveState.SWITCH_ON_DISABLED),
    DriveState.SWITCH_ON_DISABLED: (Controlword.SHUTDOWN, DriveState.READY_TO_SWITCH_ON),
    DriveState.READY_TO_SWITCH_ON: (Controlword.SWITCH_ON, DriveState.SWITCHED_ON),
    DriveState.SWITCHED_ON: (Controlword.ENABLE_OPERATION, DriveState.OPERATION_ENABLED),
}
# States the drive leaves by itself; the station only waits them out.
TRANSIENT_STATES = frozenset({DriveState.NOT_READY_TO_SWITCH_ON,
                              DriveState.FAULT_REACTION_ACTIVE})
# States in which the power stage is off: what ``disable`` must reach.
DE_ENERGISED_STATES = frozenset({DriveState.SWITCH_ON_DISABLED, DriveState.FAULT})
_STATE_POLL_S = 0.001


class StateMachine:
    """Walks one drive's CiA 402 states through the two primitives its transport offers."""

    def __init__(self, name: str, read_statusword: Callable[[], int],
                 write_controlword: Callable[[int], None], *, timeout_s: float) -> None:
        self._name = name
        self._read = read_statusword
        self._write = write_controlword
        self._timeout_s = timeout_s

    def state(self) -> DriveState:
        return decode_statusword(self._read())

    def await_state(self, accepted: frozenset[DriveState], what: str) -> DriveState:
        """Poll the statusword until the drive is in one of ``accepted`` states."""
        deadline = time.monotonic() + self._timeout_s
        while True:
            statusword = self._read()
            state = decode_statusword(statusword)
            if state in accepted:
                return state
            if time.monotonic() > deadline:
                raise DeviceStateError(
                    self._name,
                    f"{what}: still {state.value} (statusword 0x{statusword:04X}) "
                    f"after {self._timeout_s} s",
                )
            time.sleep(_STATE_POLL_S)

    def enable(self) -> None:
        """One command per step; more steps than states would mean the drive loops."""
        for _ in range(len(ENABLE_STEPS) + len(TRANSIENT_STATES) + 1):
            state = self.state()
            if state is DriveState.OPERATION_ENABLED:
                return
            if state in TRANSIENT_STATES:
                self.await_state(frozenset(DriveState) - TRANSIENT_STATES,
                                 f"waiting out {state.value}")
                continue
            command, expected = ENABLE_STEPS[state]
            if command is Controlword.FAULT_RESET:
                # Fault reset acts on the rising edge of bit 7.
                self._write(Controlword.DISABLE_VOLTAGE)
            self._write(command)
            self.await_state(frozenset({expected}), f"{command.name.lower()} from {state.value}")
        raise DeviceStateError(self._name, "the drive did not reach operation enabled")

    def disable(self) -> None:
        self._write(Controlword.DISABLE_VOLTAGE)
        self.await_state(DE_ENERGISED_STATES, "disable voltage")
