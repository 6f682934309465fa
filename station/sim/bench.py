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
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType

import can
import canopen

from drivers.canbus import DEFAULT_CHANNEL, VIRTUAL_INTERFACE
from drivers.cia301 import SYNC_COB_ID
from drivers.modbus_map import DEFAULT_UNIT_ID, ModbusLink
from station.core import Effect, LoadKind
from station.paths import sim_state_dir
from station.physics.params import UnitParams, derive_unit
from station.physics.plant import Plant
from station.serials import parse_serial
from station.sim import eeprom
from station.sim.devices import SimDrive, SimSensor
from station.sim.modbus import DEFAULT_WATCHDOG_S, SimModbusServer
from station.sim.trajectory import period_us

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
        self.unit: UnitParams = derive_unit(
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
        except BaseException:
            self.close()
            raise

    def close(self) -> None:
        """Stop the Modbus server, heartbeats, the bus reader and the bus; harmless when
        already closed."""
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
                # Pack every frame before sending any: once the first frame is out, the
                # station's threads wake up and compete for the interpreter.
                burst = [*sensor.frames(), *(drive.frames() if self.drive_on_can else ())]
                for message in burst:
                    bus.send(message)
            except Exception:
                # canopen's listener would only log the message; keep the traceback.
                _log.exception("simulated bench failed at SYNC %d", self.sync_count + 1)
                raise
