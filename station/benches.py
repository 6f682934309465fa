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

import logging
import os
import tomllib
import uuid
from collections.abc import Iterator, Mapping
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import can
import canopen

from drivers.base import AccelerationSensor, Drive
from drivers.canbus import (
    DEFAULT_SYNC_PERIOD_S,
    VIRTUAL_INTERFACE,
    BusConfig,
    PeriodicSync,
    SteppedSync,
    SyncClock,
    bench_tpdo_cob_ids,
    open_network,
)
from drivers.canopen_drive import CanopenDrive
from drivers.canopen_sensor import CanopenSensor
from station.core import Axis, Effect, LoadKind
from station.errors import DeviceError, InputError
from station.recording import RecordingMetadata, SimulatedClock
from station.serials import Serial, parse_serial
from station.sim.bench import SimBench, SimBenchConfig
from station.tomltable import TomlTable, toml_error

log = logging.getLogger(__name__)

SIM_BENCH = "sim"
"""The bench name meaning the simulated bench in this process (CLI.md)."""
BENCH_ENV = "STATION_BENCH"
DEFAULT_STATION_ID = 1
_RECEIVE_OWN = "receive_own_messages"


class Transport(StrEnum):
    """How the station reaches the drive (CLI.md: CANopen or Modbus)."""

    CANOPEN = "canopen"
    MODBUS = "modbus"


class BenchFileError(InputError):
    """A bench file that cannot be used; nothing was done (exit code 2)."""


@dataclass(frozen=True)
class Fixture:
    """How the sensor sits on the load: what the recording metadata calls the geometry."""

    tangential_axis: Axis
    gravity_axis: Axis
    radius_m: float
    gear_ratio: float  # load revolutions per motor revolution (ICD.md §5)


@dataclass(frozen=True)
class SimSettings:
    """The simulated hardware behind a simulated bench."""

    load: LoadKind = LoadKind.DISK
    unit: str | None = None  # serial on the fixture; None: the unit the operator names
    effects: frozenset[Effect] | None = None  # None: each unit's own concealed effects
    noise_ug: float | None = None  # sensor noise density; None: the unit's own
    seed: int = 0


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

    @property
    def simulated(self) -> bool:
        return self.sim is not None


SIM_SPEC = BenchSpec(name=SIM_BENCH, station_id=DEFAULT_STATION_ID, sim=SimSettings())


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
    table.finish()
    return SimSettings(load=load or LoadKind.DISK, unit=unit, effects=effects, noise_ug=noise,
                       seed=seed)


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
    if transport is Transport.MODBUS:
        top.problem("transport", "Modbus drives are not supported by this station version yet")
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
                     sync_period_s=period, fixture=fixture, sim=sim, source=source)


def load_bench(name_or_path: str | None = None) -> BenchSpec:
    """``sim`` (the default, also from ``STATION_BENCH``) or a bench file's path."""
    chosen = name_or_path or os.environ.get(BENCH_ENV) or SIM_BENCH
    if chosen == SIM_BENCH:
        return SIM_SPEC
    path = Path(chosen).expanduser()
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise BenchFileError(
            f"bench {chosen!r} is neither {SIM_BENCH!r} nor an existing bench file"
        ) from None
    except OSError as exc:
        raise BenchFileError(f"bench file {path}: cannot be read: {exc.strerror}") from None
    except UnicodeDecodeError as exc:
        raise BenchFileError(f"bench file {path}: not UTF-8 text (byte {exc.start})") from None
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
    _listeners: list[can.Listener] = field(default_factory=list)

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
            extra=dict(extra),
        )

    def recording_clock(self) -> SimulatedClock | None:
        """Simulated benches stamp frames in simulated time; real ones keep bus time."""
        return SimulatedClock(self.spec.sync_period_s) if self.spec.simulated else None

    @contextmanager
    def listening(self, *listeners: can.Listener) -> Iterator[None]:
        """Let ``listeners`` see every frame on the bus for the duration of the block."""
        notifier = self.network.notifier
        if notifier is None:
            raise DeviceError(self.spec.name, "the CAN network is not connected")
        for listener in listeners:
            notifier.add_listener(listener)
        try:
            yield
        finally:
            for listener in listeners:
                notifier.remove_listener(listener)


def _sim_fixture(bench: SimBench) -> Fixture:
    sensor = bench.unit.sensor
    return Fixture(sensor.tangential_axis, sensor.axial_axis, sensor.radius_m,
                   bench.unit.gear_ratio)


@contextmanager
def open_bench(spec: BenchSpec, serial: Serial) -> Iterator[BenchSession]:
    """Connect to the bench with the unit ``serial`` on it; everything is released on leaving.

    Closing order matters: the clock stops first, then the drive is disabled
    (its ``close``), then the bus goes, then (simulated) the devices.
    """
    with ExitStack() as stack:
        sim_bench: SimBench | None = None
        if spec.sim is not None:
            settings = spec.sim
            channel = f"station-sim-{uuid.uuid4().hex}"
            sim_bench = stack.enter_context(SimBench(SimBenchConfig(
                serial=settings.unit or serial.label,
                load=settings.load,
                effects=settings.effects,
                seed=settings.seed,
                channel=channel,
                drive_node=spec.drive_node,
                sensor_node=spec.sensor_node,
                sync_period_s=spec.sync_period_s,
                noise_density_ug=settings.noise_ug,
            )))
            bus = BusConfig(interface=VIRTUAL_INTERFACE, channel=channel,
                            options={_RECEIVE_OWN: True})
        else:
            base = spec.bus if spec.bus is not None else BusConfig.from_python_can_config()
            # The station records the SYNCs it sends itself, so it must hear its own frames.
            options = {_RECEIVE_OWN: True, **base.options}
            bus = BusConfig(base.interface, base.channel, base.bitrate, options)
        network = stack.enter_context(open_network(bus))
        drive = stack.enter_context(CanopenDrive(network, spec.drive_node))
        sensor = stack.enter_context(CanopenSensor(network, spec.sensor_node))
        clock: SyncClock
        if sim_bench is not None:
            cob_ids = bench_tpdo_cob_ids(spec.drive_node, spec.sensor_node,
                                         drive_name=drive.name, sensor_name=sensor.name)
            clock = SteppedSync(network, period_s=spec.sync_period_s, expected_cob_ids=cob_ids)
        else:
            clock = PeriodicSync(network, period_s=spec.sync_period_s)
        stack.enter_context(clock)
        fixture = spec.fixture or (_sim_fixture(sim_bench) if sim_bench is not None else None)
        if fixture is None:
            raise BenchFileError(f"bench {spec.name}: no fixture geometry")
        yield BenchSession(spec, drive, sensor, clock, network, fixture)
