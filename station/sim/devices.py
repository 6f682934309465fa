"""The bench's drive and sensor as canopen ``LocalNode``s built from the EDS files.

They answer SDOs through canopen's ``SdoServer`` (expedited and segmented);
this module supplies the device behind it. Every object's value lives in one
table per device and is served by a read callback, so what an SDO upload
returns is what the device holds; every write goes through a write callback
that validates it first and raises ``SdoAbortedError`` to refuse it. Because
``LocalNode.set_data`` only stores data after the callbacks succeed (and the
read callback never falls through to that store), a refused write changes
nothing.

Timing follows ICD.md: parameters written between SYNCs are *held* at once
(and read back) but take *effect* at the next SYNC, when the bench calls
``SimDrive.sync``. The TPDOs are packed from the devices' own mapping objects
(0x1A00..) with a precompiled ``struct``, so the EDS and the bytes on the bus
agree by construction.

All entry points that mutate a device (SDO, NMT, SYNC, ``trip``) run under the
bench's lock: canopen calls them on its notifier thread, tests may call
``trip`` from theirs.
"""

from __future__ import annotations

import logging
import struct
import threading
from collections.abc import Callable, Iterator, Mapping, Sequence
from enum import Enum, IntEnum
from pathlib import Path
from typing import Protocol

import can
import canopen
from canopen.objectdictionary import ODVariable, datatypes
from canopen.sdo.exceptions import SdoAbortedError

from drivers.base import DriveState
from drivers.eds import PERSISTED, DeviceKind, load_od
from station.cia301 import AbortCode, NmtCommand, NmtState, Signature
from station.core import (
    GAIN_UNITY,
    NOMINAL_TRIMS,
    SATURATED_COUNTS,
    SENSOR_COUNTER_MODULUS,
    SENSOR_RANGES_G,
    Trims,
)
from station.errors import DeviceError
from station.physics.plant import DriveCommand
from station.sim import trajectory as traj
from station.sim.eeprom import Eeprom, ObjectKey, key_text

_log = logging.getLogger(__name__)

Value = int | float | str


class FaultCode(IntEnum):
    """EMCY error codes (CiA 301/402) the simulated drive can trip with."""

    OVERCURRENT = 0x2310
    DC_LINK_OVERVOLTAGE = 0x3210
    DRIVE_OVERTEMPERATURE = 0x4310


class ErrorRegister(IntEnum):
    """Bits of object 0x1001 (CiA 301)."""

    GENERIC = 0x01
    CURRENT = 0x02
    VOLTAGE = 0x04
    TEMPERATURE = 0x08


_FAULT_REGISTER = {
    FaultCode.OVERCURRENT: ErrorRegister.GENERIC | ErrorRegister.CURRENT,
    FaultCode.DC_LINK_OVERVOLTAGE: ErrorRegister.GENERIC | ErrorRegister.VOLTAGE,
    FaultCode.DRIVE_OVERTEMPERATURE: ErrorRegister.GENERIC | ErrorRegister.TEMPERATURE,
}


class Obj:
    """Object dictionary keys the simulation gives behaviour to (ICD.md §2, §3)."""

    ERROR_REGISTER = (0x1001, 0)
    CYCLE_PERIOD = (0x1006, 0)
    HEARTBEAT = (0x1017, 0)
    IDENTITY_SERIAL = (0x1018, 4)
    SYNC_OVERFLOW = (0x1019, 0)
    STORE = (0x1010, 1)
    RESTORE = (0x1011, 1)
    OFFSET_A = (0x2100, 1)
    OFFSET_B = (0x2100, 2)
    GAIN_A = (0x2100, 3)
    GAIN_B = (0x2100, 4)
    MICROSTEPS = (0x2102, 0)
    AMPLITUDE = (0x2103, 0)
    CONTROLWORD = (0x6040, 0)
    STATUSWORD = (0x6041, 0)
    MODE = (0x6060, 0)
    MODE_DISPLAY = (0x6061, 0)
    POSITION_DEMAND = (0x6062, 0)
    VELOCITY_DEMAND = (0x606B, 0)
    RATED_CURRENT = (0x6075, 0)
    PROFILE_ACCELERATION = (0x6083, 0)
    PROFILE_DECELERATION = (0x6084, 0)
    TARGET_VELOCITY = (0x60FF, 0)
    SENSOR_RANGE = (0x2000, 0)
    SENSITIVITY = (0x2001, 0)
    SAMPLE_COUNTER = (0x2010, 0)
    ACCEL_X = (0x2020, 1)
    ACCEL_Y = (0x2020, 2)
    ACCEL_Z = (0x2020, 3)


TRIM_KEYS = (Obj.OFFSET_A, Obj.OFFSET_B, Obj.GAIN_A, Obj.GAIN_B)

TPDO_COMM_BASE = 0x1800
TPDO_MAP_BASE = 0x1A00
_MAX_TPDOS = 512
COB_ID_INVALID = 0x8000_0000
_COB_ID_RTR_OFF = 0x4000_0000
_CAN_ID_MASK = 0x7FF

_STRUCT_CODES = {
    datatypes.INTEGER8: "b",
    datatypes.INTEGER16: "h",
    datatypes.INTEGER32: "i",
    datatypes.UNSIGNED8: "B",
    datatypes.UNSIGNED16: "H",
    datatypes.UNSIGNED32: "I",
    datatypes.REAL32: "f",
}


# --- CiA 402 power state machine -----------------------------------------------------------

class Sw(IntEnum):
    """Statusword bits (CiA 402)."""

    READY_TO_SWITCH_ON = 0x0001
    SWITCHED_ON = 0x0002
    OPERATION_ENABLED = 0x0004
    FAULT = 0x0008
    VOLTAGE_ENABLED = 0x0010
    QUICK_STOP = 0x0020
    SWITCH_ON_DISABLED = 0x0040
    REMOTE = 0x0200
    TARGET_REACHED = 0x0400
    SPEED_ZERO = 0x1000  # profile velocity mode: "speed = 0"


# The DC link is always up on the bench and the drive always listens to the bus.
_ALWAYS = Sw.VOLTAGE_ENABLED | Sw.REMOTE

STATE_BITS: Mapping[DriveState, int] = {
    DriveState.NOT_READY_TO_SWITCH_ON: _ALWAYS,
    DriveState.SWITCH_ON_DISABLED: _ALWAYS | Sw.SWITCH_ON_DISABLED,
    DriveState.READY_TO_SWITCH_ON: _ALWAYS | Sw.QUICK_STOP | Sw.READY_TO_SWITCH_ON,
    DriveState.SWITCHED_ON: _ALWAYS | Sw.QUICK_STOP | Sw.READY_TO_SWITCH_ON | Sw.SWITCHED_ON,
    DriveState.OPERATION_ENABLED: _ALWAYS
    | Sw.QUICK_STOP
    | Sw.READY_TO_SWITCH_ON
    | Sw.SWITCHED_ON
    | Sw.OPERATION_ENABLED,
    DriveState.QUICK_STOP_ACTIVE: _ALWAYS
    | Sw.READY_TO_SWITCH_ON
    | Sw.SWITCHED_ON
    | Sw.OPERATION_ENABLED,
    DriveState.FAULT_REACTION_ACTIVE: _ALWAYS
    | Sw.READY_TO_SWITCH_ON
    | Sw.SWITCHED_ON
    | Sw.OPERATION_ENABLED
    | Sw.FAULT,
    DriveState.FAULT: _ALWAYS | Sw.FAULT,
}

FAULT_RESET_BIT = 0x0080


class Cw(Enum):
    """Device control commands encoded in controlword bits 0-3 (CiA 402)."""

    DISABLE_VOLTAGE = "disable voltage"
    QUICK_STOP = "quick stop"
    SHUTDOWN = "shutdown"
    SWITCH_ON = "switch on / disable operation"
    ENABLE_OPERATION = "enable operation"


def decode_controlword(controlword: int) -> Cw:
    if not controlword & 0x0002:
        return Cw.DISABLE_VOLTAGE
    if not controlword & 0x0004:
        return Cw.QUICK_STOP
    if not controlword & 0x0001:
        return Cw.SHUTDOWN
    if not controlword & 0x0008:
        return Cw.SWITCH_ON
    return Cw.ENABLE_OPERATION


def next_state(state: DriveState, command: Cw) -> DriveState:
    """CiA 402 transitions 2-12 for a command; quick stop behaves as option code 0.

    With option code 0 ("disable drive function") quick stop de-energises at
    once and ends in switch on disabled, which is what this drive does.
    """
    off = (Cw.DISABLE_VOLTAGE, Cw.QUICK_STOP)
    if state is DriveState.SWITCH_ON_DISABLED:
        return DriveState.READY_TO_SWITCH_ON if command is Cw.SHUTDOWN else state
    if state is DriveState.READY_TO_SWITCH_ON:
        if command in off:
            return DriveState.SWITCH_ON_DISABLED
        if command is Cw.SWITCH_ON:
            return DriveState.SWITCHED_ON
        if command is Cw.ENABLE_OPERATION:
            return DriveState.OPERATION_ENABLED  # transitions 3 + 4
        return state
    if state in (DriveState.SWITCHED_ON, DriveState.OPERATION_ENABLED):
        if command in off:
            return DriveState.SWITCH_ON_DISABLED
        if command is Cw.SHUTDOWN:
            return DriveState.READY_TO_SWITCH_ON
        if command is Cw.SWITCH_ON:
            return DriveState.SWITCHED_ON
        return DriveState.OPERATION_ENABLED
    # Fault states leave only through a fault reset (transition 15).
    return state


# --- Generic device: object table, SDO callbacks, NMT, TPDOs -------------------------------

class SensorElement(Enum):
    """The MEMS element behind the sensor node (broken ones are injected faults)."""

    SOUND = "sound"
    SATURATED = "saturated"
    UNPLUGGED = "unplugged"


class SensorPlant(Protocol):
    """The part of the plant the sensor node needs (its MEMS element)."""

    def set_sensor_range(self, range_g: int) -> None: ...

    def sensor_lsb_mps2(self) -> float: ...


class Tpdo:
    """One synchronous TPDO with its layout compiled from the mapping object."""

    def __init__(
        self,
        number: int,
        cob_id: int,
        layout: struct.Struct,
        sources: tuple[Callable[[], Value], ...],
        mapped: tuple[ObjectKey, ...],
    ) -> None:
        self.number = number
        self.layout = layout
        self.sources = sources
        self.mapped = mapped
        self.enabled = not cob_id & COB_ID_INVALID
        # Reused for every frame: the virtual bus copies a message when it is sent.
        self.message = can.Message(
            arbitration_id=cob_id & _CAN_ID_MASK,
            is_extended_id=False,
            data=bytearray(layout.size),
        )

    def frame(self) -> can.Message:
        self.layout.pack_into(self.message.data, 0, *[source() for source in self.sources])
        return self.message


class SimNode:
    """A LocalNode whose object values live in ``values`` and whose writes are checked."""

    kind: DeviceKind

    def __init__(self, node_id: int, *, period_us: int, lock: threading.RLock) -> None:
        self._node_id = node_id
        self.node = canopen.LocalNode(node_id, load_od(self.kind, node_id))
        self.variables: dict[ObjectKey, ODVariable] = dict(_variables(self.node.object_dictionary))
        self.values: dict[ObjectKey, Value] = {}
        self.power_on: dict[ObjectKey, Value] = {
            key: var.default for key, var in self.variables.items() if var.default is not None
        }
        self.power_on[Obj.CYCLE_PERIOD] = period_us
        self.values.update(self.power_on)
        self.live: dict[ObjectKey, Callable[[], Value]] = {}
        self.handlers: dict[ObjectKey, Callable[[int], None]] = {
            Obj.SYNC_OVERFLOW: self._write_sync_overflow,
        }
        self.tpdos: list[Tpdo] = []
        self.operational = False
        self.silent = False  # off the bus: hears nothing, says nothing (a fault)
        self.sdo_requests_to_drop = 0  # the next requests go unanswered (a fault)
        self.on_sdo_dropped: Callable[[], None] | None = None
        self._lock = lock
        self.node.add_read_callback(self._on_read)  # type: ignore[no-untyped-call]
        self.node.add_write_callback(self._on_write)  # type: ignore[no-untyped-call]

    @property
    def node_id(self) -> int:
        return self._node_id

    @property
    def nmt_state(self) -> NmtState:
        return NmtState(self.node.nmt._state)

    # Hooks for the subclasses --------------------------------------------------------------

    def reset_application(self) -> None:
        """What NMT "reset node" does before the communication reset."""

    def pdo_source(self, key: ObjectKey) -> Callable[[], Value]:
        """Where a mapped object's value comes from at the SYNC instant."""
        live = self.live.get(key)
        if live is not None:
            return live
        values = self.values
        return lambda: values[key]

    # Wiring -------------------------------------------------------------------------------

    def attach(self, network: canopen.Network) -> None:
        """Join ``network``, taking over NMT and SDO reception from canopen's defaults.

        canopen's NmtSlave neither reloads anything on reset nor falls silent
        when stopped, so this device handles both services itself.
        """
        network.add_node(self.node)
        node = self.node
        network.unsubscribe(0, node.nmt.on_command)
        network.subscribe(0, self._on_nmt)
        network.unsubscribe(node.sdo.rx_cobid, node.sdo.on_request)
        network.subscribe(node.sdo.rx_cobid, self._on_sdo_request)
        self.tpdos = self._compile_tpdos()

    def stop(self) -> None:
        """Stop producing heartbeats (before the bus goes away)."""
        self.node.nmt.stop_heartbeat()  # type: ignore[no-untyped-call]

    def boot(self) -> None:
        """Power on: reset node, boot-up frame, PRE-OPERATIONAL with heartbeats."""
        with self._lock:
            self._reset(NmtCommand.RESET_NODE)

    def fall_silent(self) -> None:
        """Drop off the bus for good (a dead transceiver, a cut cable): no heartbeat,
        no TPDO, no answer to SDO or NMT."""
        with self._lock:
            self.silent = True
            self.node.nmt.stop_heartbeat()  # type: ignore[no-untyped-call]

    def frames(self) -> Iterator[can.Message]:
        """This SYNC's TPDO frames, in PDO number order (only when OPERATIONAL)."""
        if self.operational and not self.silent:
            for tpdo in self.tpdos:
                if tpdo.enabled:
                    yield tpdo.frame()

    def boot_standalone(self) -> None:
        """Power on off the CAN bus (a drive reached over Modbus): no NMT, no heartbeat.

        The application starts as after NMT "reset node"; the communication
        objects already hold their power-on values.
        """
        with self._lock:
            self.reset_application()

    # Direct access (another transport: the Modbus facade) -----------------------------------

    def read_object(self, key: ObjectKey) -> int:
        """An integer object as an SDO upload gives it: live values, CiA 301 aborts."""
        return self.read_objects([key])[0]

    def read_objects(self, keys: Sequence[ObjectKey]) -> list[int]:
        """Several objects from one instant (no SYNC can fall between two of them)."""
        with self._lock:
            raws = [self.node.get_data(*key, check_readable=True) for key in keys]
        values: list[int] = []
        for key, raw in zip(keys, raws, strict=True):
            value = self.variables[key].decode_raw(raw)
            if not isinstance(value, int):
                raise TypeError(f"{key_text(key)} is not an integer object")
            values.append(value)
        return values

    def write_object(self, key: ObjectKey, value: int) -> None:
        """Write as an SDO download does, through the same checks (access, EDS range,
        then the object's handler): a refusal raises ``SdoAbortedError`` with the CiA
        301 abort code and changes nothing. Takes effect at the next SYNC, like SDO."""
        with self._lock:
            self.node.set_data(*key, self._encode(key, value), check_writable=True)

    def write_objects(self, writes: Sequence[tuple[ObjectKey, int]]) -> None:
        """Several writes as one: all of them are applied, or none is.

        Each is checked as ``write_object`` does, in order, so a later one sees the
        earlier ones (as consecutive SDO downloads would); if one is refused, the
        device state is rolled back before the abort propagates. The lock is held
        throughout, so neither a SYNC nor an SDO sees a half-applied set. Effects
        outside the device (the EEPROM file, a heartbeat producer) cannot be rolled
        back: a store belongs alone in such a set, or last.
        """
        with self._lock:
            saved = self._snapshot()
            try:
                for key, value in writes:
                    self.write_object(key, value)
            except BaseException:
                self._rollback(saved)
                raise

    def _encode(self, key: ObjectKey, value: int) -> bytes:
        # canopen's own lookup gives the SDO abort code of a missing object.
        var: ODVariable = self.node._find_object(*key)  # type: ignore[no-untyped-call]
        if var.data_type not in datatypes.INTEGER_TYPES:
            raise TypeError(f"{key_text(key)} is not an integer object")
        low, high = _type_range(var)
        if not low <= value <= high:
            raise SdoAbortedError(AbortCode.VALUE_RANGE)
        # Packed directly: ODVariable.encode_raw would log the EDS range warnings
        # that the write callback then turns into the abort.
        packed: bytes = ODVariable.STRUCT_TYPES[var.data_type].pack(value)
        return packed

    def _snapshot(self) -> tuple[dict[str, object], dict[int, dict[int, bytes]]]:
        """Everything a handler may change: this object's attributes, canopen's store.

        Kept generic (every attribute, dicts copied) so that a handler added later
        is rolled back too without anyone remembering to list what it touches.
        """
        attributes = {
            name: dict(value) if isinstance(value, dict) else value
            for name, value in vars(self).items()
        }
        stored = {index: dict(subs) for index, subs in self.node.data_store.items()}
        return attributes, stored

    def _rollback(self, saved: tuple[dict[str, object], dict[int, dict[int, bytes]]]) -> None:
        attributes, stored = saved
        for name, value in attributes.items():
            current = getattr(self, name)
            if isinstance(current, dict) and isinstance(value, dict):
                # In place: TPDO sources and live readers hold these very dicts.
                current.clear()
                current.update(value)
            else:
                setattr(self, name, value)
        self.node.data_store.clear()
        self.node.data_store.update(stored)

    # canopen callbacks ---------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: ODVariable) -> Value | None:
        key = (od.index, od.subindex)
        live = self.live.get(key)
        if live is not None:
            return live()
        return self.values.get(key)

    def _on_write(self, index: int, subindex: int, od: ODVariable, data: bytes) -> None:
        key = (od.index, od.subindex)
        value = od.decode_raw(data)
        if isinstance(value, int):
            if (od.min is not None and value < od.min) or (od.max is not None and value > od.max):
                raise SdoAbortedError(AbortCode.VALUE_RANGE)
            handler = self.handlers.get(key)
            if handler is not None:
                handler(value)
                return
        if not isinstance(value, int | float | str):
            raise SdoAbortedError(AbortCode.VALUE_RANGE)
        self.values[key] = value

    def _on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        # CiA 301: no SDO service in STOPPED; the client simply times out.
        if self.node.nmt._state == NmtState.STOPPED or self.silent:
            return
        with self._lock:
            if self.sdo_requests_to_drop > 0:
                self.sdo_requests_to_drop -= 1
                if self.on_sdo_dropped is not None:
                    self.on_sdo_dropped()
                return
            self.node.sdo.on_request(can_id, data, timestamp)  # type: ignore[no-untyped-call]

    def _on_nmt(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 2 or data[1] not in (0, self.node_id) or self.silent:
            return
        try:
            command = NmtCommand(data[0])
        except ValueError:
            return
        with self._lock:
            if command in (NmtCommand.RESET_NODE, NmtCommand.RESET_COMMUNICATION):
                self._reset(command)
            else:
                self.node.nmt.send_command(command)
                self.operational = self.nmt_state is NmtState.OPERATIONAL

    def _reset(self, command: NmtCommand) -> None:
        if command is NmtCommand.RESET_NODE:
            self.reset_application()
        for key, var in self.variables.items():
            if key[0] < 0x2000 and var.writable:
                self.values[key] = self.power_on[key]
        self._refresh_tpdo_validity()
        nmt = self.node.nmt
        self.operational = False
        nmt.stop_heartbeat()  # type: ignore[no-untyped-call]
        nmt.send_command(NmtCommand.RESET_COMMUNICATION)  # INITIALISING: boot-up frame
        nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)  # starts heartbeats from 0x1017

    # TPDOs ----------------------------------------------------------------------------------

    def _compile_tpdos(self) -> list[Tpdo]:
        tpdos: list[Tpdo] = []
        for number in range(_MAX_TPDOS):
            cob_key = (TPDO_COMM_BASE + number, 1)
            if cob_key not in self.variables:
                break
            self.handlers[cob_key] = self._cob_id_writer(number)
            mapped: list[ObjectKey] = []
            codes = "<"
            count = int(self.values[(TPDO_MAP_BASE + number, 0)])
            for sub in range(1, count + 1):
                entry = int(self.values[(TPDO_MAP_BASE + number, sub)])
                key = (entry >> 16, (entry >> 8) & 0xFF)
                var = self.variables.get(key)
                if (
                    var is None
                    or not var.pdo_mappable
                    or len(var) != entry & 0xFF
                    or var.data_type not in _STRUCT_CODES
                ):
                    raise ValueError(
                        f"{self.kind} TPDO{number + 1} maps {entry:#010x}, "
                        "which is not a PDO-mappable object of that size"
                    )
                mapped.append(key)
                codes += _STRUCT_CODES[int(var.data_type)]
            layout = struct.Struct(codes)
            if layout.size > 8:
                raise ValueError(f"{self.kind} TPDO{number + 1} maps {layout.size} bytes")
            tpdos.append(
                Tpdo(
                    number + 1,
                    int(self.values[cob_key]),
                    layout,
                    tuple(self.pdo_source(key) for key in mapped),
                    tuple(mapped),
                )
            )
        return tpdos

    def _cob_id_writer(self, number: int) -> Callable[[int], None]:
        key = (TPDO_COMM_BASE + number, 1)

        def write(cob_id: int) -> None:
            # The CAN-ID is static; only "valid" and "no RTR" may change (CiA 301).
            static = int(self.values[key]) & ~(COB_ID_INVALID | _COB_ID_RTR_OFF)
            if cob_id & ~(COB_ID_INVALID | _COB_ID_RTR_OFF) != static:
                raise SdoAbortedError(AbortCode.VALUE_RANGE)
            self.values[key] = cob_id
            self._refresh_tpdo_validity()

        return write

    def _refresh_tpdo_validity(self) -> None:
        for tpdo in self.tpdos:
            cob_id = int(self.values[(TPDO_COMM_BASE + tpdo.number - 1, 1)])
            tpdo.enabled = not cob_id & COB_ID_INVALID

    def _write_sync_overflow(self, value: int) -> None:
        if value == 1:  # CiA 301: 0 or 2..240
            raise SdoAbortedError(AbortCode.VALUE_RANGE)
        self.values[Obj.SYNC_OVERFLOW] = value


def _variables(od: canopen.ObjectDictionary) -> Iterator[tuple[ObjectKey, ODVariable]]:
    for obj in od.values():
        members = [obj] if isinstance(obj, ODVariable) else list(obj.values())
        for var in members:
            yield (var.index, var.subindex), var


# --- The stepper drive ---------------------------------------------------------------------

class SimDrive(SimNode):
    """The stepper drive of ICD.md §2: CiA 402 profile velocity with current trims."""

    kind = DeviceKind.DRIVE

    def __init__(
        self,
        node_id: int,
        *,
        serial: str,
        serial_number: int,
        rated_current_mA: int,
        microsteps: int,
        eeprom_path: Path,
        period_us: int,
        lock: threading.RLock,
    ) -> None:
        super().__init__(node_id, period_us=period_us, lock=lock)
        self.power_on[Obj.IDENTITY_SERIAL] = serial_number
        self.values[Obj.IDENTITY_SERIAL] = serial_number
        self.persisted = tuple(
            key for key, var in self.variables.items() if var.storage_location == PERSISTED
        )
        factory = {key: int(self.power_on[key]) for key in self.persisted}
        factory[Obj.RATED_CURRENT] = rated_current_mA
        factory[Obj.MICROSTEPS] = microsteps
        self.eeprom = Eeprom(eeprom_path, serial, factory)
        self.eeprom_fails = False  # every store is refused (a worn or broken EEPROM)
        self.on_store_failed: Callable[[], None] | None = None
        problems = self._image_problems(factory) + self._image_problems(self.eeprom.image())
        if problems:
            raise DeviceError("drive", f"EEPROM image {eeprom_path}: " + "; ".join(problems))
        self.period_us = period_us
        self.state = DriveState.SWITCH_ON_DISABLED
        self._controlword_prev = 0
        self.ramp = traj.STANDSTILL
        self._change = 0
        self._pending = True
        self._effective_trims = (0, 0, GAIN_UNITY, GAIN_UNITY)
        self._trims = NOMINAL_TRIMS
        self._effective_amplitude = 0
        self._effective_target = 0
        self._effective_microsteps = microsteps
        self._effective_acceleration = 1
        self._effective_deceleration = 1
        self._effective_enabled = False
        self.command = self._idle_command()
        self.live.update(
            {
                Obj.STATUSWORD: self.statusword,
                Obj.MODE_DISPLAY: lambda: self.values[Obj.MODE],
                Obj.POSITION_DEMAND: lambda: traj.position_demand(self.ramp),
                Obj.VELOCITY_DEMAND: lambda: traj.velocity_demand(self.ramp),
            }
        )
        self.handlers.update(
            {
                Obj.STORE: self._write_store,
                Obj.RESTORE: self._write_restore,
                Obj.OFFSET_A: self._write_offset(Obj.OFFSET_A),
                Obj.OFFSET_B: self._write_offset(Obj.OFFSET_B),
                Obj.GAIN_A: self._write_pending(Obj.GAIN_A),
                Obj.GAIN_B: self._write_pending(Obj.GAIN_B),
                Obj.MICROSTEPS: self._write_microsteps,
                Obj.AMPLITUDE: self._write_amplitude,
                Obj.CONTROLWORD: self._write_controlword,
                Obj.RATED_CURRENT: self._write_rated_current,
                Obj.TARGET_VELOCITY: self._write_pending(Obj.TARGET_VELOCITY),
                Obj.PROFILE_ACCELERATION: self._write_pending(Obj.PROFILE_ACCELERATION),
                Obj.PROFILE_DECELERATION: self._write_pending(Obj.PROFILE_DECELERATION),
            }
        )

    # The SYNC cycle -------------------------------------------------------------------------

    def sync(self) -> None:
        """SYNC: close the period that ended, latch held writes, plan the next period.

        The bench has already advanced the plant with ``command`` (the inputs in
        effect over the ended period); after this call ``command`` holds the
        inputs for the period that starts now, and the TPDOs report this instant.
        """
        period = self.period_us
        ramp = traj.advance(self.ramp, self._change, period)
        if self._pending:
            self._latch()
        if self._effective_enabled:
            change = traj.velocity_change(
                ramp.velocity,
                self._effective_target,
                self._effective_acceleration,
                self._effective_deceleration,
                period,
            )
        else:
            # De-energised: nothing is commanded to move, the demand stays put.
            ramp = traj.Ramp(ramp.position, 0)
            change = 0
        self.ramp = ramp
        self._change = change
        motion = traj.kinematics(ramp, change, period)
        self.command = DriveCommand(
            enabled=self._effective_enabled,
            amplitude_mA=float(self._effective_amplitude),
            trims=self._trims,
            position_start=motion.position_start,
            velocity=motion.velocity,
            acceleration=motion.acceleration,
            microsteps_per_fullstep=self._effective_microsteps,
        )

    def statusword(self) -> int:
        word = STATE_BITS[self.state]
        if self.state is DriveState.OPERATION_ENABLED:
            velocity = self.ramp.velocity
            if velocity == int(self.values[Obj.TARGET_VELOCITY]) * traj.VELOCITY_SCALE:
                word |= Sw.TARGET_REACHED
            if velocity == 0:
                word |= Sw.SPEED_ZERO
        return word

    @property
    def effective_trims(self) -> tuple[int, int, int, int]:
        """The trims in effect (those TPDO2 reports), as the drive's integers."""
        return self._effective_trims

    def communication_lost(self) -> bool:
        """React to a master that fell silent (the Modbus watchdog); True if it was running.

        Nobody supervises the motor any more, so a running drive stops: target
        velocity 0 and "disable voltage" into SWITCH ON DISABLED (CiA 402 0x6007
        option 2), from where the master must enable it again explicitly.
        """
        with self._lock:
            if self.state is not DriveState.OPERATION_ENABLED:
                return False
            self._enter(DriveState.SWITCH_ON_DISABLED)
            return True

    def power_cycle(self, *, on_can: bool = True) -> None:
        """Lose power and boot again: RAM (trims written since the last store, the
        power state) is gone; the stored parameters come back from the EEPROM."""
        with self._lock:
            if on_can:
                self._reset(NmtCommand.RESET_NODE)  # boot-up frame, then PRE-OPERATIONAL
            else:
                self.reset_application()

    def trip(self, code: FaultCode) -> None:
        """Fault the drive (fault reaction ends in FAULT): de-energise and send EMCY."""
        with self._lock:
            self._enter(DriveState.FAULT)
            register = int(_FAULT_REGISTER[code])
            self.values[Obj.ERROR_REGISTER] = register
            if self._may_send_emcy():
                self.node.emcy.send(int(code), register)

    def pdo_source(self, key: ObjectKey) -> Callable[[], Value]:
        # TPDOs report the values in effect, SDO reads the values held.
        if key in TRIM_KEYS:
            position = TRIM_KEYS.index(key)
            return lambda: self._effective_trims[position]
        if key == Obj.AMPLITUDE:
            return lambda: self._effective_amplitude
        return super().pdo_source(key)

    def reset_application(self) -> None:
        """Reboot: stored parameters from EEPROM, everything else from the EDS."""
        for key, var in self.variables.items():
            if key[0] >= 0x2000 and var.writable:
                self.values[key] = self.power_on[key]
        self.values.update(self.eeprom.image())
        self.values[Obj.AMPLITUDE] = self.values[Obj.RATED_CURRENT]
        self.values[Obj.ERROR_REGISTER] = 0
        self.state = DriveState.SWITCH_ON_DISABLED
        self._controlword_prev = 0
        self.ramp = traj.STANDSTILL
        self._change = 0
        self._latch()
        self.command = self._idle_command()

    # Internals ------------------------------------------------------------------------------

    def _latch(self) -> None:
        values = self.values
        trims = (
            int(values[Obj.OFFSET_A]),
            int(values[Obj.OFFSET_B]),
            int(values[Obj.GAIN_A]),
            int(values[Obj.GAIN_B]),
        )
        if trims != self._effective_trims:
            self._effective_trims = trims
            self._trims = Trims(*(float(t) for t in trims))
        self._effective_amplitude = int(values[Obj.AMPLITUDE])
        self._effective_target = int(values[Obj.TARGET_VELOCITY])
        self._effective_microsteps = int(values[Obj.MICROSTEPS])
        self._effective_acceleration = int(values[Obj.PROFILE_ACCELERATION])
        self._effective_deceleration = int(values[Obj.PROFILE_DECELERATION])
        self._effective_enabled = self.state is DriveState.OPERATION_ENABLED
        self._pending = False

    def _may_send_emcy(self) -> bool:
        # CiA 301: EMCY is an NMT PRE-OPERATIONAL/OPERATIONAL service.
        return self.nmt_state in (NmtState.PRE_OPERATIONAL, NmtState.OPERATIONAL)

    def _idle_command(self) -> DriveCommand:
        motion = traj.kinematics(self.ramp, 0, self.period_us)
        return DriveCommand(
            enabled=False,
            amplitude_mA=float(self._effective_amplitude),
            trims=self._trims,
            position_start=motion.position_start,
            velocity=0.0,
            acceleration=0.0,
            microsteps_per_fullstep=self._effective_microsteps,
        )

    def _enter(self, state: DriveState) -> None:
        if state is self.state:
            return
        if self.state is DriveState.OPERATION_ENABLED:
            # Leaving operation enabled de-energises; the motion demand is dropped.
            self.values[Obj.TARGET_VELOCITY] = 0
        self.state = state
        self._pending = True

    def _write_controlword(self, controlword: int) -> None:
        rising_fault_reset = bool(
            controlword & FAULT_RESET_BIT and not self._controlword_prev & FAULT_RESET_BIT
        )
        self._controlword_prev = controlword
        self.values[Obj.CONTROLWORD] = controlword
        if self.state is DriveState.FAULT:
            if rising_fault_reset:
                self._enter(DriveState.SWITCH_ON_DISABLED)
                self.values[Obj.ERROR_REGISTER] = 0
                if self._may_send_emcy():
                    self.node.emcy.reset()
            return
        self._enter(next_state(self.state, decode_controlword(controlword)))

    def _write_pending(self, key: ObjectKey) -> Callable[[int], None]:
        def write(value: int) -> None:
            self.values[key] = value
            self._pending = True

        return write

    def _write_offset(self, key: ObjectKey) -> Callable[[int], None]:
        def write(value: int) -> None:
            if 2 * abs(value) > int(self.values[Obj.RATED_CURRENT]):
                raise SdoAbortedError(AbortCode.VALUE_RANGE)
            self.values[key] = value
            self._pending = True

        return write

    def _write_amplitude(self, value: int) -> None:
        if value > int(self.values[Obj.RATED_CURRENT]):
            raise SdoAbortedError(AbortCode.VALUE_RANGE)
        self.values[Obj.AMPLITUDE] = value
        self._pending = True

    def _write_microsteps(self, value: int) -> None:
        # Any resolution in the EDS range (1..256): real drives use 200 or 250
        # too, and the plant follows the unwrapped position, so nothing here
        # needs a power of two (a reader must unwrap 0x6062 before "mod 4m").
        if self.state is DriveState.OPERATION_ENABLED:
            # The electrical angle would jump under a running motor.
            raise SdoAbortedError(AbortCode.DEVICE_STATE)
        self.values[Obj.MICROSTEPS] = value
        self._pending = True

    def _write_rated_current(self, value: int) -> None:
        values = self.values
        largest_offset = max(abs(int(values[Obj.OFFSET_A])), abs(int(values[Obj.OFFSET_B])))
        if value < int(self.values[Obj.AMPLITUDE]) or value < 2 * largest_offset:
            # The held amplitude and offsets would be out of their own ranges.
            raise SdoAbortedError(AbortCode.DEVICE_STATE)
        self.values[Obj.RATED_CURRENT] = value

    def _write_store(self, value: int) -> None:
        if value != Signature.SAVE:
            raise SdoAbortedError(AbortCode.CANNOT_STORE)
        if self.eeprom_fails:
            _log.error("drive %s: EEPROM write failed (injected fault)", self.eeprom.serial)
            if self.on_store_failed is not None:
                self.on_store_failed()
            raise SdoAbortedError(AbortCode.CANNOT_STORE)
        try:
            self.eeprom.store({key: int(self.values[key]) for key in self.persisted})
        except OSError as exc:
            _log.error("drive %s: EEPROM write failed: %s", self.eeprom.serial, exc)
            raise SdoAbortedError(AbortCode.CANNOT_STORE) from exc

    def _write_restore(self, value: int) -> None:
        if value != Signature.LOAD:
            raise SdoAbortedError(AbortCode.CANNOT_STORE)
        try:
            self.eeprom.erase()
        except OSError as exc:
            _log.error("drive %s: EEPROM erase failed: %s", self.eeprom.serial, exc)
            raise SdoAbortedError(AbortCode.CANNOT_STORE) from exc

    def _image_problems(self, image: Mapping[ObjectKey, int]) -> list[str]:
        """Why an EEPROM image could not have been stored by this drive (empty if it could)."""
        problems = []
        for key, value in image.items():
            var = self.variables[key]
            low, high = _type_range(var)
            if var.min is not None:
                low = max(low, var.min)
            if var.max is not None:
                high = min(high, var.max)
            if not low <= value <= high:
                problems.append(f"{key_text(key)} = {value} outside {low}..{high}")
        rated = image.get(Obj.RATED_CURRENT, 0)
        for key in (Obj.OFFSET_A, Obj.OFFSET_B):
            if 2 * abs(image.get(key, 0)) > rated:
                problems.append(f"{key_text(key)} = {image[key]} exceeds half the rated current")
        return problems


def _type_range(var: ODVariable) -> tuple[int, int]:
    bits = len(var)
    if var.data_type in datatypes.SIGNED_TYPES:
        return -(1 << (bits - 1)), (1 << (bits - 1)) - 1
    return 0, (1 << bits) - 1


# --- The acceleration sensor ----------------------------------------------------------------

class SimSensor(SimNode):
    """The MEMS node of ICD.md §3: one sample per SYNC from the plant's accelerometer."""

    kind = DeviceKind.SENSOR

    def __init__(
        self,
        node_id: int,
        plant: SensorPlant,
        *,
        period_us: int,
        lock: threading.RLock,
    ) -> None:
        super().__init__(node_id, period_us=period_us, lock=lock)
        self.plant = plant
        self.element = SensorElement.SOUND
        self.live[Obj.SENSITIVITY] = plant.sensor_lsb_mps2
        self.handlers[Obj.SENSOR_RANGE] = self._write_range

    def sample(self, counts: tuple[int, int, int]) -> None:
        """SYNC: take the sample the plant produced for this instant (already
        quantised and saturated at ±32767 by the sensor model)."""
        if self.element is SensorElement.SATURATED:
            # A MEMS element gone to a rail (a shock, a latched self-test): full scale.
            counts = tuple(  # type: ignore[assignment]
                SATURATED_COUNTS if c >= 0 else -SATURATED_COUNTS for c in counts
            )
        elif self.element is SensorElement.UNPLUGGED:
            # The node still streams, but the SPI bus to the element reads zeros.
            counts = (0, 0, 0)
        values = self.values
        values[Obj.SAMPLE_COUNTER] = (int(values[Obj.SAMPLE_COUNTER]) + 1) % SENSOR_COUNTER_MODULUS
        values[Obj.ACCEL_X], values[Obj.ACCEL_Y], values[Obj.ACCEL_Z] = counts

    def reset_application(self) -> None:
        for key in self.variables:
            if key[0] >= 0x2000:
                self.values[key] = self.power_on[key]
        self.plant.set_sensor_range(int(self.values[Obj.SENSOR_RANGE]))

    def _write_range(self, range_g: int) -> None:
        if range_g not in SENSOR_RANGES_G:
            raise SdoAbortedError(AbortCode.VALUE_RANGE)
        self.plant.set_sensor_range(range_g)
        self.values[Obj.SENSOR_RANGE] = range_g
