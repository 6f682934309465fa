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
import math
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
from station.recording import SimulatedClock
from station.serials import Serial, parse_serial
from station.sim.bench import SimBench, SimBenchConfig

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


class _Table:
    """Strict reading of one TOML table: every key taken once, leftovers are errors."""

    def __init__(self, data: Mapping[str, Any], path: str, problems: list[str]) -> None:
        self._data = dict(data)
        self._path = path
        self._problems = problems

    def _where(self, key: str) -> str:
        return f"{self._path}.{key}" if self._path else key

    def take(self, key: str, kind: type | tuple[type, ...], default: Any = ...) -> Any:
        if key not in self._data:
            if default is ...:
                self._problems.append(f"{self._where(key)}: missing")
            return None if default is ... else default
        value = self._data.pop(key)
        if isinstance(value, bool) and bool not in (kind if isinstance(kind, tuple) else (kind,)):
            self._problems.append(f"{self._where(key)}: expected a number, got {value!r}")
            return None if default is ... else default
        if not isinstance(value, kind):
            self._problems.append(f"{self._where(key)}: malformed value {value!r}")
            return None if default is ... else default
        return value

    def table(self, key: str) -> _Table | None:
        value = self.take(key, dict, None)
        return None if value is None else _Table(value, self._where(key), self._problems)

    def check(self, key: str, ok: bool, message: str) -> None:
        if not ok:
            self._problems.append(f"{self._where(key)}: {message}")

    def finish(self) -> None:
        for key in self._data:
            self._problems.append(f"{self._where(key)}: unknown key")


def _axis(table: _Table, key: str) -> Axis | None:
    text = table.take(key, str)
    if text is None:
        return None
    try:
        return Axis(text.lower())
    except ValueError:
        table.check(key, False, f"must be x, y or z, not {text!r}")
        return None


def _node(table: _Table | None, key: str, default: int) -> int:
    if table is None:
        return default
    node: int = table.take(key, int, default)
    table.check(key, 1 <= node <= 127, f"node-ID must be 1..127, not {node}")
    return node


def _fixture(table: _Table | None) -> Fixture | None:
    if table is None:
        return None
    tangential = _axis(table, "tangential_axis")
    gravity = _axis(table, "gravity_axis")
    radius = table.take("radius_m", (int, float))
    ratio = table.take("gear_ratio", (int, float))
    for key, value in (("radius_m", radius), ("gear_ratio", ratio)):
        if value is not None:
            table.check(key, math.isfinite(value) and value > 0, f"must be positive, not {value}")
    table.check("gravity_axis", tangential is None or tangential != gravity,
                "gravity cannot act along the tangential axis of a horizontal load")
    table.finish()
    if tangential is None or gravity is None or radius is None or ratio is None:
        return None
    return Fixture(tangential, gravity, float(radius), float(ratio))


def _sim(table: _Table | None) -> SimSettings | None:
    if table is None:
        return None
    load_text = table.take("load", str, LoadKind.DISK.value)
    unit = table.take("unit", str, None)
    effects_list = table.take("effects", list, None)
    noise = table.take("noise_ug", (int, float), None)
    seed = table.take("seed", int, 0)
    table.finish()
    load = LoadKind.DISK
    try:
        load = LoadKind(load_text)
    except ValueError:
        table.check("load", False, f"must be one of {[k.value for k in LoadKind]}")
    if unit is not None:
        try:
            unit = parse_serial(unit).label
        except InputError as exc:
            table.check("unit", False, str(exc))
    effects: frozenset[Effect] | None = None
    if effects_list is not None:
        try:
            effects = frozenset(Effect(e) for e in effects_list)
        except ValueError:
            table.check("effects", False,
                        f"must name effects from {[e.value for e in Effect]}, not {effects_list}")
    if noise is not None:
        table.check("noise_ug", math.isfinite(noise) and noise >= 0, "must be >= 0")
    return SimSettings(load=load, unit=unit, effects=effects,
                       noise_ug=None if noise is None else float(noise), seed=seed)


def parse_bench(text: str, *, source: str) -> BenchSpec:
    """A bench file's spec; every problem in one ``BenchFileError`` naming the field."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise BenchFileError(f"bench file {source}: not valid TOML: {exc}") from None
    problems: list[str] = []
    top = _Table(doc, "", problems)
    name = top.take("name", str, Path(source).stem)
    station_id = top.take("station_id", int, DEFAULT_STATION_ID)
    top.check("station_id", 0 <= station_id <= 0xFFFF, "must fit 0x2101:02 (U16)")
    transport_text = top.take("transport", str, Transport.CANOPEN.value)
    period = top.take("sync_period_s", (int, float), DEFAULT_SYNC_PERIOD_S)
    top.check("sync_period_s", 1e-4 <= period <= 0.1, "must be 0.0001..0.1 s")
    bus_table = top.take("bus", dict, None)
    nodes = top.table("nodes")
    drive_node, sensor_node = _node(nodes, "drive", 1), _node(nodes, "sensor", 16)
    if nodes is not None:
        nodes.finish()
    fixture = _fixture(top.table("fixture"))
    sim = _sim(top.table("sim"))
    top.finish()
    top.check("nodes", drive_node != sensor_node, "drive and sensor need different node-IDs")
    transport = Transport.CANOPEN
    try:
        transport = Transport(transport_text)
    except ValueError:
        top.check("transport", False, f"must be one of {[t.value for t in Transport]}")
    top.check("transport", transport is Transport.CANOPEN,
              "Modbus drives are not supported by this station version yet")
    bus: BusConfig | None = None
    if bus_table is not None:
        try:
            bus = BusConfig.from_mapping(bus_table)
        except InputError as exc:
            top.check("bus", False, str(exc))
    if sim is not None:
        top.check("bus", bus is None or bus.interface == VIRTUAL_INTERFACE,
                  "a simulated bench lives on python-can's virtual bus")
    else:
        top.check("fixture", fixture is not None, "a real bench must describe its fixture")
    if problems:
        raise BenchFileError(f"bench file {source}:\n  " + "\n  ".join(problems))
    return BenchSpec(name=name, station_id=station_id, transport=transport, bus=bus,
                     drive_node=drive_node, sensor_node=sensor_node, sync_period_s=float(period),
                     fixture=fixture, sim=sim, source=source)


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
