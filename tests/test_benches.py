"""Bench files and the bench name (station.benches): parsing only, no bench is opened."""

from __future__ import annotations

import time
from pathlib import Path

import can
import pytest

from drivers.canbus import BusConfig, BusMonitor, bench_tpdo_cob_ids
from drivers.modbus_map import ModbusLink
from drivers.transports import Transport
from station.bench_names import BENCH_ENV, SIM_BENCH, SIM_MODBUS_BENCH, BenchFileError
from station.benches import (
    SIM_SPEC,
    BenchSpec,
    Fixture,
    load_bench,
    open_bench,
    parse_bench,
)
from station.cia301 import SYNC_COB_ID
from station.core import Axis, Effect, LoadKind
from station.errors import ExitCode, InputError
from station.serials import parse_serial
from station.simsettings import SimSettings

REAL = """\
name = "line3"
station_id = 7
transport = "canopen"
sync_period_s = 0.002

[bus]
interface = "socketcan"
channel = "can0"
bitrate = 500000

[nodes]
drive = 2
sensor = 20

[fixture]
tangential_axis = "x"
gravity_axis = "Z"
radius_m = 0.1
gear_ratio = 1
"""

FIXTURE = """
[fixture]
tangential_axis = "y"
gravity_axis = "z"
radius_m = 0.05
gear_ratio = 0.142857
"""


def refusal(text: str, source: str = "bench.toml") -> str:
    """The message a bench file is refused with; always an input error (exit code 2)."""
    with pytest.raises(BenchFileError) as caught:
        parse_bench(text, source=source)
    assert isinstance(caught.value, InputError)
    assert caught.value.exit_code is ExitCode.USAGE
    message = str(caught.value)
    assert message.startswith(f"bench file {source}")
    return message


# --- the simulated bench by name --------------------------------------------------------------


def test_sim_is_the_default_bench() -> None:
    spec = load_bench()
    assert spec is SIM_SPEC
    assert spec.name == SIM_BENCH == "sim"
    assert spec.simulated and spec.sim == SimSettings()
    assert (spec.drive_node, spec.sensor_node, spec.transport) == (1, 16, Transport.CANOPEN)
    assert load_bench("sim") is SIM_SPEC


def test_the_bench_comes_from_station_bench_when_none_is_named(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "line3.toml"
    path.write_text(REAL, encoding="utf-8")
    monkeypatch.setenv(BENCH_ENV, str(path))
    assert load_bench().name == "line3"
    assert load_bench("sim") is SIM_SPEC  # a named bench wins over the environment
    monkeypatch.setenv(BENCH_ENV, "sim")
    assert load_bench() is SIM_SPEC


# --- real benches -----------------------------------------------------------------------------


def test_a_real_bench_file_parses_to_its_spec() -> None:
    spec = parse_bench(REAL, source="benches/line3.toml")
    assert spec == BenchSpec(
        name="line3",
        station_id=7,
        transport=Transport.CANOPEN,
        bus=BusConfig(interface="socketcan", channel="can0", bitrate=500000),
        drive_node=2,
        sensor_node=20,
        sync_period_s=0.002,
        fixture=Fixture(Axis.X, Axis.Z, 0.1, 1.0),
        sim=None,
        source="benches/line3.toml",
    )
    assert not spec.simulated
    assert spec.bus is not None and dict(spec.bus.options) == {}


def test_a_minimal_real_bench_takes_defaults_and_its_name_from_the_file() -> None:
    spec = parse_bench(FIXTURE, source="/etc/station/bench-7.toml")
    assert spec.name == "bench-7"
    assert (spec.station_id, spec.drive_node, spec.sensor_node) == (1, 1, 16)
    assert spec.bus is None  # python-can's own configuration when opened
    assert spec.sync_period_s == 0.001
    assert spec.fixture == Fixture(Axis.Y, Axis.Z, 0.05, 0.142857)


def test_extra_bus_keys_are_python_can_options() -> None:
    text = REAL.replace('bitrate = 500000', 'bitrate = 500000\nfd = true')
    spec = parse_bench(text, source="b.toml")
    assert spec.bus is not None and dict(spec.bus.options) == {"fd": True}


def test_load_bench_reads_a_bench_file_by_path(tmp_path: Path) -> None:
    path = tmp_path / "line3.toml"
    path.write_text(REAL, encoding="utf-8")
    spec = load_bench(str(path))
    assert spec.source == str(path)
    assert spec.fixture == Fixture(Axis.X, Axis.Z, 0.1, 1.0)


def test_unknown_keys_are_named_at_the_top_level_and_in_tables() -> None:
    text = REAL.replace('transport = "canopen"', 'transport = "canopen"\ncolour = "blue"')
    text = text.replace("sensor = 20", "sensor = 20\nmotor = 3")
    text = text.replace("radius_m = 0.1", "radius_mm = 100")
    message = refusal(text)
    lines = message.splitlines()[1:]
    assert "  colour: unknown key" in lines
    assert "  nodes.motor: unknown key" in lines
    assert "  fixture.radius_mm: unknown key (did you mean 'radius_m'?)" in lines
    assert "  fixture.radius_m: missing" in lines


def test_a_real_bench_without_a_fixture_is_refused() -> None:
    text = REAL.split("[fixture]", maxsplit=1)[0]
    message = refusal(text)
    assert "fixture: missing: a real bench must describe its fixture" in message


MODBUS_TCP = """
[modbus]
link = "tcp"
host = "192.168.0.20"
port = 1502
unit = 3
guard_s = 0.05
"""


def test_a_modbus_bench_file_names_its_link_and_timing() -> None:
    spec = parse_bench(REAL.replace('transport = "canopen"', 'transport = "modbus"') + MODBUS_TCP,
                       source="line3.toml")
    assert spec.transport is Transport.MODBUS and not spec.sees_drive_angle
    assert spec.modbus is not None
    endpoint = spec.modbus.endpoint
    assert (endpoint.link, endpoint.host, endpoint.port, endpoint.unit) == (
        ModbusLink.TCP, "192.168.0.20", 1502, 3)
    assert spec.modbus.timing.guard_s == 0.05
    assert spec.modbus.timing.acceleration == 200_000  # the drive's shipped profile


def test_a_real_modbus_bench_without_its_link_is_refused() -> None:
    message = refusal(REAL.replace('transport = "canopen"', 'transport = "modbus"'))
    assert "modbus: missing" in message


@pytest.mark.parametrize(("old", "new", "expected"), [
    ('link = "tcp"', 'link = "rtu"', "modbus.device: missing"),
    ('unit = 3', 'unit = 300', "modbus.unit: must be in 1..247"),
    ('guard_s = 0.05', 'guard_s = -1', "modbus.guard_s"),
    ('port = 1502', 'parity = "X"', "modbus.parity: must be N, E or O"),
    ('port = 1502', 'baud = 9600', "modbus.baud"),
])
def test_a_bad_modbus_table_names_the_field(old: str, new: str, expected: str) -> None:
    text = REAL.replace('transport = "canopen"', 'transport = "modbus"')
    message = refusal(text + MODBUS_TCP.replace(old, new))
    assert expected in message


def test_a_modbus_table_on_a_canopen_bench_is_refused() -> None:
    assert "modbus: only used with transport" in refusal(REAL + MODBUS_TCP)


def test_sim_modbus_is_the_simulated_bench_with_a_modbus_drive() -> None:
    spec = load_bench(SIM_MODBUS_BENCH)
    assert spec.simulated and spec.transport is Transport.MODBUS
    assert spec.modbus is not None and spec.modbus.endpoint.link is ModbusLink.TCP


def test_an_unknown_transport_names_the_choices() -> None:
    message = refusal(REAL.replace('transport = "canopen"', 'transport = "ethercat"'))
    assert "transport: must be one of 'canopen', 'modbus', got 'ethercat'" in message
    assert "not supported" not in message


@pytest.mark.parametrize(
    ("old", "new", "expected"),
    [
        ("drive = 2", "drive = 128", "nodes.drive: must be in 1..127, got 128"),
        ("drive = 2", "drive = 20", "nodes.sensor: the drive and the sensor need different"),
        ("station_id = 7", "station_id = 70000", "station_id: must be in 0..65535, got 70000"),
        ("sync_period_s = 0.002", "sync_period_s = 1", "sync_period_s: must be in [0.0001, 0.1]"),
        ('gravity_axis = "Z"', 'gravity_axis = "x"', "fixture.gravity_axis: gravity cannot act"),
        ('gravity_axis = "Z"', 'gravity_axis = "w"', "gravity_axis: must be x, y or z, got 'w'"),
        ("radius_m = 0.1", "radius_m = -0.1", "fixture.radius_m: must be > 0, got -0.1"),
        ("station_id = 7", "station_id = true", "station_id: expected an integer, got a boolean"),
        ('interface = "socketcan"', 'interface = "nonsense"', "bus: CAN interface 'nonsense'"),
    ],
)
def test_a_bad_value_is_refused_naming_its_field(old: str, new: str, expected: str) -> None:
    text = REAL.replace(old, new)
    assert text != REAL
    assert expected in refusal(text)


def test_every_problem_of_a_file_is_reported_at_once() -> None:
    text = REAL.replace("drive = 2", "drive = 0").replace('transport = "canopen"',
                                                          'transport = "modbus"')
    message = refusal(text)
    assert "nodes.drive" in message and "modbus: missing" in message


# --- simulated benches in a file --------------------------------------------------------------


def test_a_sim_bench_file_may_name_another_unit_its_effects_and_noise() -> None:
    text = """\
name = "rehearsal"

[sim]
unit = "SN42"
effects = ["friction", "detent_torque"]
noise_ug = 400
load = "belt"
seed = 3
"""
    spec = parse_bench(text, source="rehearsal.toml")
    assert spec.simulated
    assert spec.sim == SimSettings(
        load=LoadKind.BELT,
        unit="SN42",
        effects=frozenset({Effect.FRICTION, Effect.DETENT_TORQUE}),
        noise_ug=400.0,
        seed=3,
    )
    assert spec.fixture is None and spec.bus is None


def test_a_sim_bench_with_no_effects_listed_is_not_one_with_its_own_effects() -> None:
    spec = parse_bench("[sim]\neffects = []\n", source="quiet.toml")
    assert spec.sim is not None and spec.sim.effects == frozenset()
    spec = parse_bench("[sim]\n", source="own.toml")
    assert spec.sim == SimSettings()


def test_a_sim_bench_may_draw_its_fixture_on_the_virtual_bus() -> None:
    spec = parse_bench('[bus]\ninterface = "virtual"\n[sim]\n' + FIXTURE, source="wrong.toml")
    assert spec.bus is not None and spec.bus.interface == "virtual"
    assert spec.fixture == Fixture(Axis.Y, Axis.Z, 0.05, 0.142857)


def test_a_sim_bench_on_a_non_virtual_bus_is_refused() -> None:
    text = '[bus]\ninterface = "socketcan"\nchannel = "can0"\n[sim]\nunit = "SN42"\n'
    assert "bus: a simulated bench lives on python-can's virtual bus" in refusal(text)


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        ('unit = "123"', "sim.unit: serial '123' is malformed"),
        ('effects = ["gremlins"]', "sim.effects: unknown effects ['gremlins']"),
        ("noise_ug = -1", "sim.noise_ug: must be >= 0"),
        ('load = "flywheel"', "sim.load: must be one of 'disk', 'belt', got 'flywheel'"),
        ("noise = 3", "sim.noise: unknown key"),
    ],
)
def test_bad_sim_settings_are_refused_naming_the_field(line: str, expected: str) -> None:
    assert expected in refusal(f"[sim]\n{line}\n")


# --- unusable files ---------------------------------------------------------------------------


def test_bad_toml_is_a_bench_file_error() -> None:
    message = refusal('name = "line3\n[nodes\n')
    assert "invalid TOML" in message


def test_a_missing_bench_file_is_refused(tmp_path: Path) -> None:
    missing = tmp_path / "nowhere.toml"
    expected = r"neither a built-in bench \(sim, sim-modbus\) nor an existing bench file"
    with pytest.raises(BenchFileError, match=expected) as caught:
        load_bench(str(missing))
    assert isinstance(caught.value, InputError)


def test_a_bench_path_that_is_a_directory_is_refused(tmp_path: Path) -> None:
    with pytest.raises(BenchFileError, match="cannot be read"):
        load_bench(str(tmp_path))


def test_a_bench_file_that_is_not_utf8_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "latin1.toml"
    path.write_bytes('name = "bänk"\n'.encode("latin-1"))
    with pytest.raises(BenchFileError, match=r"latin1\.toml"):
        load_bench(str(path))


class _Heard(can.Listener):
    def __init__(self) -> None:
        self.frames: list[int] = []

    def on_message_received(self, msg: can.Message) -> None:
        self.frames.append(msg.arbitration_id)


def test_a_listener_has_heard_every_answer_to_every_sync_when_the_run_returns(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """A recording closes as soon as its run returns. The station's other listeners
    are slowed here after every answer, so a listener served after them would
    still be waiting for the last answer when the block ends."""
    monitor = BusMonitor.on_message_received

    def slow_monitor(self: BusMonitor, msg: can.Message) -> None:
        if msg.arbitration_id != SYNC_COB_ID:
            time.sleep(0.02)
        monitor(self, msg)

    monkeypatch.setattr(BusMonitor, "on_message_received", slow_monitor)
    heard = _Heard()
    with open_bench(SIM_SPEC, parse_serial("SN123")) as session:
        session.sensor.set_range_g(2)
        with session.listening(heard):
            session.clock.advance(5)
    answers = set(bench_tpdo_cob_ids(SIM_SPEC.drive_node, SIM_SPEC.sensor_node))
    after_syncs = [f for f in heard.frames if f == SYNC_COB_ID or f in answers]
    assert after_syncs.count(SYNC_COB_ID) == 5
    assert len(after_syncs) == 5 * (1 + len(answers))
    assert after_syncs[-1] in answers
