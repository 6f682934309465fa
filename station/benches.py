"""Which bench the station talks to, and opening it as the drive and sensor roles.

CLI.md: ``--bench NAME|PATH`` (or ``STATION_BENCH``). ``sim``, the default,
is the simulated bench inside the station process: the unit the operator
names sits on python-can's ``virtual`` bus as simulated CANopen devices. A
bench file (TOML) names a real CAN interface by python-can configuration, the
node-IDs, the fixture geometry and the drive transport. The procedure sees
neither: it gets a ``BenchSession`` holding a ``Drive``, an
``AccelerationSensor`` and a SYNC clock.

A bench file may also describe a simulated bench (a ``[sim]`` table): a
different unit on the fixture than the one named, a noisier sensor, a
fixture drawn differently from how the sensor is really mounted. That is how
the station's refusals are exercised without hardware, and how a technician
rehearses a fault.
"""

from __future__ import annotations

import importlib
import logging
import tomllib
import uuid
from collections.abc import Callable, Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import TYPE_CHECKING, Any, Final

import can
import canopen

from drivers.base import AccelerationSensor, Drive
from drivers.canbus import (
    DEFAULT_SYNC_PERIOD_S,
    VIRTUAL_INTERFACE,
    BusConfig,
    BusMonitor,
    PeriodicSync,
    SteppedSync,
    SyncClock,
    Taps,
    bench_tpdo_cob_ids,
    open_network,
)
from drivers.canopen_drive import CanopenDrive
from drivers.canopen_sensor import CanopenSensor
from drivers.modbus_drive import ModbusDrive, ModbusEndpoint
from drivers.modbus_map import (
    DEFAULT_UNIT_ID,
    PTY_PARITY,
    ModbusLink,
)
from drivers.transports import Transport, drive_traits
from station.analysis.commanded import CommandTiming
from station.bench_names import (
    SIM_BENCH,
    SIM_MODBUS_BENCH,
    BenchFileError,
    chosen_bench,
    read_bench_file,
)
from station.core import Axis, Effect, LoadKind
from station.errors import DeviceError, InputError
from station.recorder import SimulatedClock
from station.recording import RecordingMetadata
from station.serials import Serial, parse_serial
from station.simsettings import COUNTED_KINDS, Fault, FaultKind, SimSettings
from station.tomltable import TomlTable, toml_error

if TYPE_CHECKING:
    from station.sim.bench import SimBench, SimBenchConfig

SimulatorFactory = Callable[["SimBenchConfig"], "SimBench"]
"""Builds a simulated bench's devices from their configuration (``station.sim.bench``)."""

log = logging.getLogger(__name__)

DEFAULT_STATION_ID = 1
_RECEIVE_OWN = "receive_own_messages"
SIMULATOR: Final = "station.sim.bench"
"""The simulated bench's module, imported only when a bench is simulated (as python-can
imports an interface's module only when it is named): the runtime never needs the
simulator, and the simulator builds on the runtime (import-linter holds both)."""


@dataclass(frozen=True)
class Fixture:
    """How the sensor sits on the load: what the recording metadata calls the geometry."""

    tangential_axis: Axis
    gravity_axis: Axis
    radius_m: float
    gear_ratio: float  # load revolutions per motor revolution (ICD.md §5)


DEFAULT_GUARD_S = 0.02
"""After a Modbus write is acknowledged, samples this much later are trusted to show it:
the drive applies a write at its next internal cycle (1 ms on typical drives)."""
DEFAULT_DRIVE_ACCELERATION = 200_000
"""Microsteps/s²: the drive's profile acceleration as shipped (ICD.md's EDS, 0x6083)."""


DEFAULT_ENDPOINT: Final = ModbusEndpoint(ModbusLink.TCP)
DEFAULT_TIMING: Final = CommandTiming(DEFAULT_GUARD_S, DEFAULT_DRIVE_ACCELERATION)


@dataclass(frozen=True)
class ModbusSettings:
    """How a Modbus drive is reached, and what the station assumes about its timing."""

    endpoint: ModbusEndpoint = DEFAULT_ENDPOINT
    timing: CommandTiming = DEFAULT_TIMING


@dataclass(frozen=True)
class BenchSpec:
    name: str
    station_id: int
    transport: Transport = Transport.CANOPEN
    bus: BusConfig | None = None  # None: python-can's own configuration (real) / virtual (sim)
    drive_node: int = 1
    sensor_node: int = 16
    sync_period_s: float = DEFAULT_SYNC_PERIOD_S
    fixture: Fixture | None = None  # None on a simulated bench: as the simulator mounts it
    sim: SimSettings | None = None
    source: str = SIM_BENCH
    modbus: ModbusSettings | None = None  # with transport MODBUS
    # What builds the simulated devices of a simulated bench: the simulator's own
    # ``SimBench``, loaded by name, when None. Tests inject one that watches the benches
    # a calibration opens (as python-can takes a bus class): never a flag in the runtime.
    simulator: SimulatorFactory | None = field(default=None, compare=False, repr=False)

    @property
    def simulated(self) -> bool:
        return self.sim is not None

    @property
    def sees_drive_angle(self) -> bool:
        """Whether the drive's position demand is on the bus with every SYNC: asked of the
        transport's driver (``drivers.transports``), before anything is opened."""
        return drive_traits(self.transport).reports_state


SIM_SPEC = BenchSpec(name=SIM_BENCH, station_id=DEFAULT_STATION_ID, sim=SimSettings())
SIM_MODBUS_SPEC = BenchSpec(name=SIM_MODBUS_BENCH, station_id=DEFAULT_STATION_ID,
                            transport=Transport.MODBUS, sim=SimSettings(),
                            source=SIM_MODBUS_BENCH, modbus=ModbusSettings())
BUILT_IN_BENCHES = {SIM_BENCH: SIM_SPEC, SIM_MODBUS_BENCH: SIM_MODBUS_SPEC}


# --- bench files ------------------------------------------------------------------------------


def _axis(table: TomlTable, key: str) -> Axis | None:
    """x, y or z, in either case: datasheets print axes in capitals."""
    text = table.string(key)
    if not table.valid(key):
        return None
    try:
        return Axis(text.lower())
    except ValueError:
        table.problem(key, f"must be x, y or z, got {text!r}")
        return None


def _fixture(table: TomlTable | None) -> Fixture | None:
    if table is None:
        return None
    tangential = _axis(table, "tangential_axis")
    gravity = _axis(table, "gravity_axis")
    radius = table.real("radius_m", gt=0)
    ratio = table.real("gear_ratio", gt=0)
    if tangential is not None and tangential == gravity:
        table.problem("gravity_axis", "gravity cannot act along the tangential axis of a "
                      "load turning about a vertical axis")
    table.finish()
    if tangential is None or gravity is None:
        return None
    return Fixture(tangential, gravity, radius, ratio)


def _sim(table: TomlTable | None) -> SimSettings | None:
    if table is None:
        return None
    load = table.choice("load", LoadKind) if table.has("load") else LoadKind.DISK
    unit = table.string("unit") if table.has("unit") else None
    if unit is not None and table.valid("unit"):
        try:
            unit = parse_serial(unit).label
        except InputError as exc:
            table.problem("unit", str(exc))
    effects: frozenset[Effect] | None = None
    if table.has("effects"):
        names = table.str_array("effects")
        unknown = sorted(set(names) - {e.value for e in Effect})
        if unknown:
            table.problem("effects", f"unknown effects {unknown}; known: "
                          f"{', '.join(e.value for e in Effect)}")
        effects = frozenset(Effect(n) for n in names if n not in unknown)
    noise = table.real("noise_ug", ge=0) if table.has("noise_ug") else None
    seed = table.integer("seed", 0) if table.has("seed") else 0
    faults = tuple(_fault(entry) for entry in table.table_array("faults")
                   ) if table.has("faults") else ()
    table.finish()
    return SimSettings(load=load or LoadKind.DISK, unit=unit, effects=effects, noise_ug=noise,
                       seed=seed, faults=tuple(f for f in faults if f is not None))


def _fault(table: TomlTable) -> Fault | None:
    """``[[sim.faults]]``: kind, at_s (simulated seconds after power-on), count."""
    kind = table.choice("kind", FaultKind)
    at_s = table.real("at_s", ge=0, le=3600) if table.has("at_s") else 0.0
    count = 1
    if table.has("count"):
        count = table.integer("count", 1, 10_000)
        if kind is not None and kind not in COUNTED_KINDS:
            table.problem("count", f"means nothing for {kind.value}: it happens once and lasts")
    table.finish()
    if kind is None or not table.valid("at_s", "count"):
        return None
    return Fault(kind, at_s, count)


def _modbus(table: TomlTable | None, *, simulated: bool) -> ModbusSettings | None:
    if table is None:
        return None
    base = ModbusSettings()
    at, timing = base.endpoint, base.timing
    link = table.choice("link", ModbusLink) if table.has("link") else at.link
    host = table.string("host", nonempty=True) if table.has("host") else at.host
    port = table.integer("port", 1, 65535) if table.has("port") else at.port
    device = table.string("device", nonempty=True) if table.has("device") else at.device
    baudrate = table.integer("baudrate", 1200, 921600) if table.has("baudrate") else at.baudrate
    parity = table.string("parity") if table.has("parity") else at.parity
    if table.valid("parity") and parity not in ("N", "E", "O"):
        table.problem("parity", f"must be N, E or O, got {parity!r}")
    unit = table.integer("unit", 1, 247, note="Modbus unit IDs") if table.has("unit") else at.unit
    timeout = table.real("timeout_s", gt=0, le=10) if table.has("timeout_s") else at.timeout_s
    guard = table.real("guard_s", ge=0, le=1) if table.has("guard_s") else timing.guard_s
    acceleration = (table.real("acceleration", gt=0) if table.has("acceleration")
                    else timing.acceleration)
    if link is ModbusLink.RTU and not device and not simulated:
        table.problem("device", "missing: an RTU link needs its serial device (e.g. /dev/ttyUSB0)")
    table.finish()
    endpoint = ModbusEndpoint(link or at.link, host, port, device, baudrate, parity, unit,
                              timeout)
    return ModbusSettings(endpoint, CommandTiming(guard, acceleration))


def _node(table: TomlTable | None, key: str, default: int) -> int:
    if table is None or not table.has(key):
        return default
    return table.integer(key, 1, 127)


def parse_bench(text: str, *, source: str) -> BenchSpec:
    """A bench file's spec; every problem in one ``BenchFileError`` naming the field."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise BenchFileError(f"bench file {source}: {toml_error(exc)}") from None
    problems: list[str] = []
    top = TomlTable(problems, "", doc)
    name = top.string("name", nonempty=True) if top.has("name") else Path(source).stem
    station_id = (
        top.integer("station_id", 0, 0xFFFF, note="0x2101:02 is a U16")
        if top.has("station_id") else DEFAULT_STATION_ID
    )
    transport = top.choice("transport", Transport) if top.has("transport") else Transport.CANOPEN
    period = (
        top.real("sync_period_s", ge=1e-4, le=0.1)
        if top.has("sync_period_s") else DEFAULT_SYNC_PERIOD_S
    )
    bus_settings = top.mapping("bus")
    nodes = top.optional_table("nodes")
    drive_node, sensor_node = _node(nodes, "drive", 1), _node(nodes, "sensor", 16)
    if nodes is not None:
        if nodes.valid("drive", "sensor") and drive_node == sensor_node:
            nodes.problem("sensor", "the drive and the sensor need different node-IDs")
        nodes.finish()
    fixture = _fixture(top.optional_table("fixture"))
    sim = _sim(top.optional_table("sim"))
    modbus = _modbus(top.optional_table("modbus"), simulated=sim is not None)
    if transport is Transport.MODBUS and modbus is None:
        if sim is None:
            top.problem("modbus", "missing: a Modbus drive needs its link (tcp or rtu) and address")
        else:
            modbus = ModbusSettings()
    if transport is not Transport.MODBUS and top.has("modbus"):
        top.problem("modbus", "only used with transport = \"modbus\"")
    bus: BusConfig | None = None
    if bus_settings is not None:
        try:
            bus = BusConfig.from_mapping(bus_settings)
        except InputError as exc:
            top.problem("bus", str(exc))
    if sim is not None and bus is not None and bus.interface != VIRTUAL_INTERFACE:
        top.problem("bus", "a simulated bench lives on python-can's virtual bus")
    if sim is None and not top.has("fixture"):
        top.problem("fixture", "missing: a real bench must describe its fixture")
    top.finish()
    if problems:
        raise BenchFileError(f"bench file {source}:\n  " + "\n  ".join(problems))
    return BenchSpec(name=name, station_id=station_id, transport=transport or Transport.CANOPEN,
                     bus=bus, drive_node=drive_node, sensor_node=sensor_node,
                     sync_period_s=period, fixture=fixture, sim=sim, source=source,
                     modbus=modbus if transport is Transport.MODBUS else None)


def load_bench(name_or_path: str | None = None) -> BenchSpec:
    """``sim`` (the default, also from ``STATION_BENCH``) or a bench file's path."""
    chosen = chosen_bench(name_or_path)
    if chosen in BUILT_IN_BENCHES:
        return BUILT_IN_BENCHES[chosen]
    path, text = read_bench_file(chosen)
    return parse_bench(text, source=str(path))


# --- sessions ---------------------------------------------------------------------------------


@dataclass
class BenchSession:
    """An open bench: the roles the procedure uses, and the bus to listen on."""

    spec: BenchSpec
    drive: Drive
    sensor: AccelerationSensor
    clock: SyncClock
    network: canopen.Network
    fixture: Fixture
    bus_monitor: BusMonitor
    taps: Taps

    def supervise(self) -> None:
        """Raise if the bus went off or a device fell silent or rebooted (no bus traffic).

        The clock calls this while it runs, so a run stops within moments of
        such a fault, before anything measured after it could be used.
        """
        self.bus_monitor.check()
        self.drive.check_alive()
        self.sensor.check_alive()

    @property
    def command_timing(self) -> CommandTiming | None:
        """For a drive that reports nothing on the bus: how the station times its writes."""
        modbus = self.spec.modbus
        return modbus.timing if modbus is not None and not self.drive.reports_state else None

    def recording_metadata(self, serial: str, *, microsteps: int, rotor_teeth: int,
                           rated_current_mA: int, extra: Mapping[str, Any]) -> RecordingMetadata:
        """ICD.md §5 metadata of a recording made on this bench now.

        Nodes and SYNC period come from the bench, geometry from its fixture and
        the LSB from the sensor (so its range must already be set); the drive's
        figures are passed in because every caller has read them already.
        """
        fixture = self.fixture
        return RecordingMetadata(
            serial=serial,
            drive_node=self.spec.drive_node,
            sensor_node=self.spec.sensor_node,
            sync_period_s=self.spec.sync_period_s,
            microsteps_per_fullstep=microsteps,
            rotor_teeth=rotor_teeth,
            rated_current_mA=rated_current_mA,
            sensor_lsb_mps2=self.sensor.lsb_mps2(),
            tangential_axis=fixture.tangential_axis,
            sensor_radius_m=fixture.radius_m,
            gear_ratio=fixture.gear_ratio,
            extra={"drive_transport": self.spec.transport.value, **extra},
        )

    def recording_clock(self) -> SimulatedClock | None:
        """Simulated benches stamp frames in simulated time; real ones keep bus time."""
        return SimulatedClock(self.spec.sync_period_s) if self.spec.simulated else None

    @contextmanager
    def listening(self, *listeners: can.Listener) -> Iterator[None]:
        """Let ``listeners`` see every frame on the bus for the duration of the block.

        They see a frame before the clock counts it, so when the block ends
        they have seen every answer to every SYNC the run sent.
        """
        if self.network.notifier is None:
            raise DeviceError(self.spec.name, "the CAN network is not connected")
        self.taps.add(*listeners)
        try:
            yield
        finally:
            self.taps.remove(*listeners)


def _sim_fixture(bench: SimBench) -> Fixture:
    sensor = bench.unit.sensor
    return Fixture(sensor.tangential_axis, sensor.axial_axis, sensor.radius_m,
                   bench.unit.gear_ratio)


def _open_drive(spec: BenchSpec, network: canopen.Network, sim_bench: SimBench | None) -> Drive:
    """The drive role over the bench's transport (a simulated Modbus drive: its own server)."""
    if spec.transport is Transport.CANOPEN:
        return CanopenDrive(network, spec.drive_node)
    endpoint = (spec.modbus or ModbusSettings()).endpoint
    if sim_bench is None:
        return ModbusDrive(endpoint)
    server = sim_bench.modbus
    if server is None:
        raise DeviceError(spec.name, "the simulated bench started no Modbus server")
    if endpoint.link is ModbusLink.TCP:
        host, port = server.tcp_address
        return ModbusDrive(replace(endpoint, host=host, port=port))
    # A pseudo-terminal refuses parity settings; the simulated line is 8N1.
    return ModbusDrive(replace(endpoint, device=server.serial_port, parity=PTY_PARITY))


@contextmanager
def open_bench(spec: BenchSpec, serial: Serial) -> Iterator[BenchSession]:
    """Connect to the bench with the unit ``serial`` on it; everything is released on leaving.

    Closing order matters: the clock stops first, then the drive is disabled
    (its ``close``), then (simulated) the devices go, then the bus.
    """
    with ExitStack() as stack:
        sim_bench: SimBench | None = None
        if spec.sim is not None:
            channel = f"station-sim-{uuid.uuid4().hex}"
            bus = BusConfig(interface=VIRTUAL_INTERFACE, channel=channel,
                            options={_RECEIVE_OWN: True})
        else:
            base = spec.bus if spec.bus is not None else BusConfig.from_python_can_config()
            # The station records the SYNCs it sends itself, so it must hear its own frames.
            options = {_RECEIVE_OWN: True, **base.options}
            bus = BusConfig(base.interface, base.channel, base.bitrate, options)
        # The station's bus joins first. python-can's virtual bus hands a frame to
        # the channel's buses in the order they joined: were the devices first, a
        # station thread preempted half-way through sending a SYNC would hear the
        # devices' answers before its own echo, and record them a sample early.
        # On a real bus the echo can never trail the answers to it.
        taps = Taps()
        network = stack.enter_context(open_network(bus, taps=taps))
        monitor = BusMonitor(bus.describe())
        if network.notifier is not None:
            network.notifier.add_listener(monitor)
        if spec.sim is not None:
            settings = spec.sim
            simulator = importlib.import_module(SIMULATOR)
            factory = spec.simulator or simulator.SimBench
            sim_bench = stack.enter_context(factory(simulator.SimBenchConfig(
                serial=settings.unit or serial.label,
                load=settings.load if settings.drawn is None else settings.drawn.load,
                effects=settings.effects,
                seed=settings.seed,
                channel=channel,
                drive_node=spec.drive_node,
                sensor_node=spec.sensor_node,
                sync_period_s=spec.sync_period_s,
                noise_density_ug=settings.noise_ug,
                drive_link=spec.modbus.endpoint.link if spec.modbus is not None else None,
                modbus_unit=(spec.modbus.endpoint.unit if spec.modbus is not None
                             else DEFAULT_UNIT_ID),
                faults=settings.faults,
                unit=settings.drawn,
            )))
        drive = stack.enter_context(_open_drive(spec, network, sim_bench))
        sensor = stack.enter_context(CanopenSensor(network, spec.sensor_node))
        clock: SyncClock
        if sim_bench is not None:
            cob_ids = bench_tpdo_cob_ids(spec.drive_node, spec.sensor_node,
                                         drive_name=drive.name, sensor_name=sensor.name)
            if not drive.reports_state:
                # The drive is not on the CAN bus: only the sensor answers each SYNC.
                cob_ids = {cob: who for cob, who in cob_ids.items() if who == sensor.name}
            clock = SteppedSync(network, period_s=spec.sync_period_s, expected_cob_ids=cob_ids)
        else:
            clock = PeriodicSync(network, period_s=spec.sync_period_s)
        stack.enter_context(clock)
        fixture = spec.fixture or (_sim_fixture(sim_bench) if sim_bench is not None else None)
        if fixture is None:
            raise BenchFileError(f"bench {spec.name}: no fixture geometry")
        session = BenchSession(spec, drive, sensor, clock, network, fixture, monitor, taps)
        clock.supervise(session.supervise)
        yield session
