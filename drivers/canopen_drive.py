"""The bench's stepper drive over CANopen (ICD.md §2), as a ``drivers.base.Drive``.

Connecting happens in the constructor: the node is attached, checked to be a
stepper drive (0x1000) and started (NMT OPERATIONAL, confirmed by its
heartbeat), because a drive that does not stream its PDOs is useless to every
procedure and failing early names the problem. Leaving the object (``close``
or the ``with`` block) always tries to de-energise the motor first.

Every device failure surfaces as a station error that keeps the device's own
evidence: the SDO abort code, or which object timed out.
"""

from __future__ import annotations

import logging
import time
from enum import IntEnum

import canopen

from drivers.base import LIVENESS_TIMEOUT_S, CalibrationRecord, DeviceIdentity, Drive, DriveState
from drivers.canbus import (
    HeartbeatWatch,
    SdoChannel,
    attach_remote_node,
    check_alive,
    check_node_id,
    detach_remote_node,
    send_nmt,
    start_node,
)
from drivers.cia402 import StateMachine
from drivers.eds import DeviceKind, load_od
from station.cia301 import NmtCommand, NmtState, Signature
from station.core import Trims
from station.errors import DeviceError, DeviceStateError, DeviceTimeout, StationError

log = logging.getLogger(__name__)


class DriveObject(IntEnum):
    """Object indices of ICD.md §2."""

    DEVICE_TYPE = 0x1000
    STORE_PARAMETERS = 0x1010
    IDENTITY = 0x1018
    TRIMS = 0x2100
    CALIBRATION_RECORD = 0x2101
    MICROSTEPS = 0x2102
    AMPLITUDE = 0x2103
    CONTROLWORD = 0x6040
    STATUSWORD = 0x6041
    MODES_OF_OPERATION = 0x6060
    MODES_OF_OPERATION_DISPLAY = 0x6061
    RATED_CURRENT = 0x6075
    TARGET_VELOCITY = 0x60FF


class TrimSub(IntEnum):
    """Sub-indices of 0x2100, in the order the drive's TPDO2 carries them."""

    OFFSET_A = 1
    OFFSET_B = 2
    GAIN_A = 3
    GAIN_B = 4


class CalibrationSub(IntEnum):
    """Sub-indices of 0x2101."""

    CALIBRATED_AT = 1
    STATION_ID = 2
    COUNT = 3


PROFILE_VELOCITY_MODE = 3
STEPPER_DRIVE_DEVICE_TYPE = 0x00030192
STORE_ON_COMMAND = 0x01
"""Bit 0 of a 0x1010 read: the device saves parameters when commanded."""
STORE_ALL_SUB = 1

_STATE_POLL_S = 0.001


class CanopenDrive(Drive):
    """A CiA 402 stepper drive with current trims, reached by SDO on ``network``."""

    def __init__(
        self,
        network: canopen.Network,
        node_id: int = 1,
        *,
        name: str = "drive",
        sdo_timeout_s: float = 0.5,
        state_timeout_s: float = 0.5,
        nmt_timeout_s: float = 1.0,
        reset_timeout_s: float = 5.0,
        store_timeout_s: float = 3.0,
        object_dictionary: canopen.ObjectDictionary | None = None,
    ) -> None:
        self.name = name
        self._network = network
        self._node_id = node_id
        self._state_timeout_s = state_timeout_s
        self._nmt_timeout_s = nmt_timeout_s
        self._reset_timeout_s = reset_timeout_s
        self._store_timeout_s = store_timeout_s
        self._closed = False
        check_node_id(node_id, name)
        od = (
            object_dictionary
            if object_dictionary is not None
            else load_od(DeviceKind.DRIVE, node_id)
        )
        self._node = attach_remote_node(network, node_id, od, name)
        try:
            self._sdo = SdoChannel(self._node, name, sdo_timeout_s)
            self._heartbeat = HeartbeatWatch(self._node)
            self._machine = StateMachine(name, self.statusword, self._command,
                                         timeout_s=state_timeout_s)
            device_type = self._sdo.read_int(DriveObject.DEVICE_TYPE)
            if device_type != STEPPER_DRIVE_DEVICE_TYPE:
                raise DeviceError(
                    name,
                    f"node {node_id} reports device type 0x{device_type:08X}, "
                    f"not a stepper drive (0x{STEPPER_DRIVE_DEVICE_TYPE:08X})",
                )
            start_node(network, node_id, self._heartbeat, name, timeout_s=nmt_timeout_s)
            # Boot-ups from here on are the station's own resets, or a fault.
            self._boots_expected = self._heartbeat.boots
        except BaseException:
            detach_remote_node(network, self._node)
            raise

    @property
    def node_id(self) -> int:
        return self._node_id

    # -- identity and ratings -------------------------------------------------

    def identity(self) -> DeviceIdentity:
        return self._sdo.identity()

    def rated_current_mA(self) -> int:
        return self._sdo.read_int(DriveObject.RATED_CURRENT)

    def microsteps_per_fullstep(self) -> int:
        return self._sdo.read_int(DriveObject.MICROSTEPS)

    # -- CiA 402 power state machine ------------------------------------------

    def statusword(self) -> int:
        return self._sdo.read_int(DriveObject.STATUSWORD)

    def state(self) -> DriveState:
        return self._machine.state()

    def _command(self, controlword: int) -> None:
        self._sdo.write(DriveObject.CONTROLWORD, 0, int(controlword))

    def _select_profile_velocity(self) -> None:
        self._sdo.write(DriveObject.MODES_OF_OPERATION, 0, PROFILE_VELOCITY_MODE)
        deadline = time.monotonic() + self._state_timeout_s
        while (mode := self._sdo.read_int(DriveObject.MODES_OF_OPERATION_DISPLAY)) != (
            PROFILE_VELOCITY_MODE
        ):
            if time.monotonic() > deadline:
                raise DeviceStateError(
                    self.name, f"mode display 0x6061 shows {mode}, not profile velocity (3)"
                )
            time.sleep(_STATE_POLL_S)

    def enable(self) -> None:
        # A stale target velocity would start the motor the moment it is enabled.
        self._sdo.write(DriveObject.TARGET_VELOCITY, 0, 0)
        self._select_profile_velocity()
        self._machine.enable()

    def disable(self) -> None:
        self._sdo.write(DriveObject.TARGET_VELOCITY, 0, 0)
        self._machine.disable()

    # -- set-points ------------------------------------------------------------

    def set_velocity(self, microsteps_per_s: int) -> None:
        self._sdo.write(DriveObject.TARGET_VELOCITY, 0, microsteps_per_s)

    def set_amplitude(self, amplitude_mA: int) -> None:
        self._sdo.write(DriveObject.AMPLITUDE, 0, amplitude_mA)

    # -- trims -----------------------------------------------------------------

    def write_trims(self, trims: Trims) -> None:
        """Write all four trims, or none: a refused value rolls back those already written.

        "None" is about what the drive holds afterwards (and could store), not
        about time: each SDO takes effect at the next SYNC (ICD.md §2), so with
        a free-running SYNC a few samples may carry a mix of old and new values.
        Analysis therefore segments by the trims in effect (TPDO2), never by
        when the station wrote them.
        """
        values = dict(zip(TrimSub, self._stored_form(trims), strict=True))
        for sub, value in values.items():
            self._sdo.check(DriveObject.TRIMS, sub, value)
        previous = self._read_trim_values()
        written: list[TrimSub] = []
        try:
            for sub, value in values.items():
                self._sdo.write(DriveObject.TRIMS, sub, value)
                written.append(sub)
        except StationError:
            self._roll_back(written, previous)
            raise

    def _roll_back(self, written: list[TrimSub], previous: dict[TrimSub, int]) -> None:
        for sub in reversed(written):
            try:
                self._sdo.write(DriveObject.TRIMS, sub, previous[sub])
            except StationError as exc:
                log.error("%s: could not restore trim 0x2100:%02X: %s", self.name, sub, exc)

    def _read_trim_values(self) -> dict[TrimSub, int]:
        return {sub: self._sdo.read_int(DriveObject.TRIMS, sub) for sub in TrimSub}

    def read_trims(self) -> Trims:
        values = self._read_trim_values()
        return Trims(
            offset_a_mA=float(values[TrimSub.OFFSET_A]),
            offset_b_mA=float(values[TrimSub.OFFSET_B]),
            gain_a=float(values[TrimSub.GAIN_A]),
            gain_b=float(values[TrimSub.GAIN_B]),
        )

    # -- persistence -----------------------------------------------------------

    def store(self) -> None:
        with self._sdo.timeout(self._store_timeout_s):
            self._sdo.write(DriveObject.STORE_PARAMETERS, STORE_ALL_SUB, Signature.SAVE)
        # The download was acknowledged; the device must also claim to save on command.
        capability = self._sdo.read_int(DriveObject.STORE_PARAMETERS, STORE_ALL_SUB)
        if not capability & STORE_ON_COMMAND:
            raise DeviceError(
                self.name, f"0x1010:01 reads 0x{capability:08X}: the drive does not save on command"
            )

    def reset(self) -> None:
        """NMT reset node, wait for the boot-up frame, then start the node again."""
        seen = self._heartbeat.sequence
        send_nmt(self._network, NmtCommand.RESET_NODE, self._node_id)
        if not self._heartbeat.wait_for(
            NmtState.BOOT_UP, after=seen, timeout_s=self._reset_timeout_s
        ):
            raise DeviceTimeout(self.name, f"no boot-up within {self._reset_timeout_s} s of reset")
        self._boots_expected = self._heartbeat.boots
        start_node(
            self._network, self._node_id, self._heartbeat, self.name, timeout_s=self._nmt_timeout_s
        )

    def read_calibration_record(self) -> CalibrationRecord:
        return CalibrationRecord(
            calibrated_at=self._sdo.read_int(
                DriveObject.CALIBRATION_RECORD, CalibrationSub.CALIBRATED_AT
            ),
            station_id=self._sdo.read_int(
                DriveObject.CALIBRATION_RECORD, CalibrationSub.STATION_ID
            ),
            count=self._sdo.read_int(DriveObject.CALIBRATION_RECORD, CalibrationSub.COUNT),
        )

    def write_calibration_record(self, record: CalibrationRecord) -> None:
        values = {
            CalibrationSub.CALIBRATED_AT: record.calibrated_at,
            CalibrationSub.STATION_ID: record.station_id,
            CalibrationSub.COUNT: record.count,
        }
        for sub, value in values.items():
            self._sdo.check(DriveObject.CALIBRATION_RECORD, sub, value)
        for sub, value in values.items():
            self._sdo.write(DriveObject.CALIBRATION_RECORD, sub, value)

    # -- liveness --------------------------------------------------------------

    def heartbeat_age_s(self) -> float | None:
        """Seconds since the drive's last heartbeat; ``None`` before the first one."""
        return self._heartbeat.age_s()

    def check_alive(self, max_age_s: float = LIVENESS_TIMEOUT_S) -> None:
        """Raise unless a heartbeat came within ``max_age_s`` and no unasked boot-up did."""
        check_alive(self._heartbeat, self._sdo, self.name, max_age_s=max_age_s,
                    boots_expected=self._boots_expected)

    # -- teardown --------------------------------------------------------------

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self.disable()
        except StationError as exc:
            log.warning("%s: could not disable on close: %s", self.name, exc)
        finally:
            detach_remote_node(self._network, self._node)
