"""The simulated bench: one unit's drive and the fixture's sensor on a virtual CAN bus.

The bench runs in simulated time. Nothing moves between SYNCs; each SYNC the
station sends advances the plant by exactly one period, so a run is
deterministic whatever the host's speed, and the station may go as fast as the
bus lets it. Per SYNC, in this order: (1) the plant is advanced over the period
that just ended with the drive's inputs in effect; (2) writes held since the
last SYNC take effect; (3) the OPERATIONAL devices send their TPDOs sampled at
this instant: sensor TPDO1 first, then drive TPDO1 and TPDO2.

The drive may instead be reached over Modbus (``SimBenchConfig.drive_link``,
ICD.md §4): it is then off the CAN bus (no NMT, SDO, heartbeat or PDO) and boots
by itself at power-on, but its cycle still runs at every SYNC, so the plant
follows its commands; only the sensor answers SYNC on the bus.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from types import TracebackType

import can
import canopen

from drivers.base import DriveState, decode_statusword
from drivers.canbus import DEFAULT_CHANNEL, VIRTUAL_INTERFACE
from drivers.modbus_map import DEFAULT_UNIT_ID, ModbusLink
from station.cia301 import SYNC_COB_ID
from station.core import NOMINAL_TRIMS, Effect, LoadKind, Trims
from station.paths import sim_state_dir
from station.physics.params import UnitParams, derive_unit
from station.physics.plant import Plant
from station.serials import parse_serial
from station.sim import eeprom
from station.sim.devices import TRIM_KEYS, SensorElement, SimDrive, SimSensor
from station.sim.faults import FaultLog, bus_error_frame, bus_off_frame
from station.sim.modbus import DEFAULT_WATCHDOG_S, SimModbusServer
from station.sim.trajectory import period_us
from station.simsettings import Fault, FaultKind

_log = logging.getLogger(__name__)


_NOTIFIER_CYCLE_S = 0.05
"""How long the bus reader may block: bounds how long ``close`` waits for it."""


@dataclass(frozen=True)
class SimBenchConfig:
    serial: str = "SN123"
    load: LoadKind = LoadKind.DISK
    effects: frozenset[Effect] | None = None  # None: the unit's own (from its serial)
    seed: int = 0
    channel: str = DEFAULT_CHANNEL  # python-can virtual bus channel
    drive_node: int = 1
    sensor_node: int = 16
    sync_period_s: float = 0.001
    substeps: int = 8
    noise_density_ug: float | None = None
    drive_link: ModbusLink | None = None  # None: the drive is on the CAN bus (CANopen)
    modbus_unit: int = DEFAULT_UNIT_ID
    modbus_watchdog_s: float = DEFAULT_WATCHDOG_S  # 0: no communication watchdog
    faults: tuple[Fault, ...] = ()  # injected, in simulated time since power-on
    # A unit given whole (``station.sim.population``) in place of the serial's own: its
    # load, effects and noise are its own, so those above must be left as they are.
    unit: UnitParams | None = None

    def __post_init__(self) -> None:
        if self.unit is None:
            return
        if self.unit.serial != self.serial:
            raise ValueError(f"the bench's unit is {self.unit.serial}, not {self.serial}")
        if (self.effects is not None or self.noise_density_ug is not None
                or self.load is not self.unit.load):
            raise ValueError("a unit given whole brings its own load, effects and noise")


@dataclass(frozen=True)
class DriveSnapshot:
    """The simulated drive as the station leaves it: what a soak run must check."""

    state: DriveState
    ram_trims: Trims  # the trims held in RAM (in effect from the next SYNC)
    stored_trims: Trims  # the trims a power cycle would bring back (the EEPROM's)

    @property
    def enabled(self) -> bool:
        return self.state is DriveState.OPERATION_ENABLED

    def trims_against(self, last_stored: Trims | None) -> TrimsLeft:
        """The trims left against the last calibration stored in the unit (None: factory)."""
        if self.stored_trims != (last_stored if last_stored is not None else NOMINAL_TRIMS):
            return TrimsLeft.EEPROM_DIFFERS
        if self.ram_trims != self.stored_trims:
            return TrimsLeft.RAM_DIFFERS
        return TrimsLeft.AS_STORED


class TrimsLeft(Enum):
    """How a drive's trims compare with its last stored calibration, checked EEPROM first:
    the EEPROM is what every later power-up runs with."""

    AS_STORED = "as stored"
    EEPROM_DIFFERS = "EEPROM differs"
    RAM_DIFFERS = "RAM differs"


class SimBench:
    """A unit (drive + plant) and a sensor answering on python-can's virtual bus.

    ``start`` boots both devices (boot-up frame, PRE-OPERATIONAL, heartbeats);
    ``close`` stops everything and is safe to call twice. As a context manager
    the bench is started on entry and closed on exit.
    """

    def __init__(self, config: SimBenchConfig, *, state_dir: Path | None = None) -> None:
        if config.drive_link is None and config.drive_node == config.sensor_node:
            raise ValueError(f"drive and sensor cannot share node-ID {config.drive_node}")
        self.config = config
        serial = parse_serial(config.serial)
        self.unit: UnitParams = config.unit or derive_unit(
            serial.label,
            load=config.load,
            effects=config.effects,
            noise_density_ug=config.noise_density_ug,
        )
        self.plant = Plant(
            self.unit,
            sync_period_s=config.sync_period_s,
            substeps=config.substeps,
            seed=config.seed,
        )
        self.sync_count = 0
        self._lock = threading.RLock()
        period = period_us(config.sync_period_s)
        self.drive = SimDrive(
            config.drive_node,
            serial=serial.label,
            serial_number=self.unit.serial_number,
            rated_current_mA=self.unit.rated_current_mA,
            microsteps=self.unit.microsteps,
            eeprom_path=eeprom.file_for(state_dir or sim_state_dir(), serial.label),
            period_us=period,
            lock=self._lock,
        )
        self.sensor = SimSensor(config.sensor_node, self.plant, period_us=period, lock=self._lock)
        self._network: canopen.Network | None = None
        self._bus: can.BusABC | None = None
        self._modbus: SimModbusServer | None = None
        self._closed = False
        self.faults = FaultLog(config.faults)
        self._schedule: dict[int, list[Fault]] = {}
        for fault in config.faults:
            self._schedule.setdefault(fault.at_sync(config.sync_period_s), []).append(fault)
        self._sensor_frames_to_drop: list[Fault] = []
        self._error_frames_to_send: list[Fault] = []
        self.at_close: DriveSnapshot | None = None

    @property
    def drive_on_can(self) -> bool:
        """Whether the drive is a CANopen node on the bus (else it is reached over Modbus)."""
        return self.config.drive_link is None

    @property
    def modbus(self) -> SimModbusServer | None:
        """The drive's running Modbus server; None for a CANopen drive or a closed bench."""
        return self._modbus

    def start(self) -> None:
        """Connect to the virtual bus and power the devices on; no-op when running."""
        if self._closed:
            raise RuntimeError("a closed bench cannot be started again")
        if self._network is not None:
            return
        bus = can.Bus(
            interface=VIRTUAL_INTERFACE, channel=self.config.channel, receive_own_messages=False
        )
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = _NOTIFIER_CYCLE_S
        self._network, self._bus = network, bus
        try:
            if self.drive_on_can:
                self.drive.attach(network)
            self.sensor.attach(network)
            network.subscribe(SYNC_COB_ID, self._on_sync)
            network.connect()
            if self.drive_on_can:
                self.drive.boot()
            else:
                self.drive.boot_standalone()
            self.sensor.boot()
            link = self.config.drive_link
            if link is not None:
                self._modbus = SimModbusServer(
                    self.drive,
                    link,
                    unit=self.config.modbus_unit,
                    watchdog_s=self.config.modbus_watchdog_s,
                )
                self._modbus.start()
            with self._lock:
                self._inject(self._schedule.pop(0, []))
        except BaseException:
            self.close()
            raise

    def snapshot(self) -> DriveSnapshot:
        """The drive's power state and trims, in RAM and in its EEPROM, right now."""
        drive = self.drive
        with self._lock:
            state = decode_statusword(drive.statusword())
            ram = Trims(*(float(drive.values[key]) for key in TRIM_KEYS))
        image = drive.eeprom.image()
        stored = Trims(*(float(image[key]) for key in TRIM_KEYS))
        return DriveSnapshot(state, ram, stored)

    def close(self) -> None:
        """Stop the Modbus server, heartbeats, the bus reader and the bus; harmless when
        already closed. The drive as the station left it is kept in ``at_close``."""
        if not self._closed and self._network is not None:
            self.at_close = self.snapshot()
            if self.at_close.enabled:
                _log.error("simulated drive %s left enabled by the station", self.config.serial)
        self._closed = True
        modbus, self._modbus = self._modbus, None
        network, self._network, self._bus = self._network, None, None
        try:
            if modbus is not None:
                modbus.close()
        finally:
            if network is not None:
                if self.drive_on_can:
                    self.drive.stop()
                self.sensor.stop()
                network.disconnect()

    def __enter__(self) -> SimBench:
        self.start()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        bus = self._bus
        if bus is None:
            return
        drive, sensor = self.drive, self.sensor
        with self._lock:
            try:
                counts = self.plant.advance(drive.command)
                drive.sync()
                sensor.sample(counts)
                self.sync_count += 1
                if self._schedule:
                    self._inject(self._schedule.pop(self.sync_count, []))
                # Pack every frame before sending any: once the first frame is out, the
                # station's threads wake up and compete for the interpreter.
                burst = [*sensor.frames(), *(drive.frames() if self.drive_on_can else ())]
                if self._sensor_frames_to_drop or self._error_frames_to_send:
                    burst = self._disturb(burst)
                for message in burst:
                    bus.send(message)
            except Exception:
                # canopen's listener would only log the message; keep the traceback.
                _log.exception("simulated bench failed at SYNC %d", self.sync_count + 1)
                raise

    # Fault injection (under the bench lock) ---------------------------------------------

    def _inject(self, faults: list[Fault]) -> None:
        for fault in faults:
            self._arm(fault)

    def _arm(self, fault: Fault) -> None:
        drive, log, sync = self.drive, self.faults, self.sync_count
        kind = fault.kind
        _log.warning("injecting %s at SYNC %d", fault, sync)

        def noted(what: str) -> Callable[[], None]:
            return lambda: log.took_effect(fault, self.sync_count, what)

        if kind is FaultKind.SDO_TIMEOUT:
            if self._modbus is not None:
                self._modbus.drop_requests(fault.count, noted("Modbus request unanswered"))
            else:
                drive.sdo_requests_to_drop += fault.count
                drive.on_sdo_dropped = noted("SDO request unanswered")
        elif kind is FaultKind.EEPROM_FAILURE:
            drive.eeprom_fails = True
            drive.on_store_failed = noted("store refused")
        elif kind in (FaultKind.SENSOR_FRAMES_LOST, FaultKind.ERROR_FRAMES):
            queue = (self._sensor_frames_to_drop if kind is FaultKind.SENSOR_FRAMES_LOST
                     else self._error_frames_to_send)
            queue.extend([fault] * fault.count)
        else:
            self._strike(fault)
            log.took_effect(fault, sync, kind.value)

    def _strike(self, fault: Fault) -> None:
        """Faults that happen at once and last."""
        drive, sensor, kind = self.drive, self.sensor, fault.kind
        if kind is FaultKind.DRIVE_SILENT:
            if self._modbus is not None:
                self._modbus.silence()
            else:
                drive.fall_silent()
            # The drive's own reaction to losing its master (CiA 402 0x6007, "disable
            # voltage"), as a real drive's heartbeat consumer or watchdog would.
            drive.communication_lost()
        elif kind is FaultKind.SENSOR_SILENT:
            sensor.fall_silent()
        elif kind is FaultKind.BUS_OFF:
            # The station's controller reports it; SocketCAN restarts it after restart-ms.
            if self._bus is not None:
                self._bus.send(bus_off_frame())
        elif kind is FaultKind.POWER_CYCLE:
            drive.power_cycle(on_can=self.drive_on_can)
        elif kind is FaultKind.SENSOR_SATURATED:
            sensor.element = SensorElement.SATURATED
        elif kind is FaultKind.SENSOR_UNPLUGGED:
            sensor.element = SensorElement.UNPLUGGED

    def _disturb(self, burst: list[can.Message]) -> list[can.Message]:
        """This SYNC's frames with a lost sensor TPDO or an error frame, as scheduled."""
        if self._sensor_frames_to_drop:
            fault = self._sensor_frames_to_drop.pop()
            cob_id = self.sensor.tpdos[0].message.arbitration_id if self.sensor.tpdos else -1
            burst = [m for m in burst if m.arbitration_id != cob_id]
            self.faults.took_effect(fault, self.sync_count, "sensor TPDO1 lost")
        if self._error_frames_to_send:
            fault = self._error_frames_to_send.pop()
            burst.append(bus_error_frame())
            self.faults.took_effect(fault, self.sync_count, "error frame")
        return burst
