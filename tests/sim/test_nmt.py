"""NMT of the simulated devices: boot-up, heartbeats, reset node and reset communication."""

from __future__ import annotations

import itertools
import statistics
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from station.sim.bench import SimBench
from tests.sim import Frame, Station, running, unique_config

BOOT_UP, PRE_OPERATIONAL, OPERATIONAL, STOPPED = 0x00, 0x7F, 0x05, 0x04


@pytest.fixture
def bench_station(tmp_path: Path) -> Iterator[tuple[SimBench, Station]]:
    with running(tmp_path / "eeprom") as pair:
        yield pair


def _listen(bus: can.BusABC, seconds: float) -> list[Frame]:
    frames = []
    deadline = time.monotonic() + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(timeout=remaining)
        if msg is not None:
            frames.append(Frame(msg.arbitration_id, bytes(msg.data), time.monotonic()))
    return frames


def test_devices_boot_up_then_send_pre_operational_heartbeats_every_100_ms(
    tmp_path: Path,
) -> None:
    config = unique_config()
    bus = can.Bus(interface="virtual", channel=config.channel, receive_own_messages=False)
    try:
        with SimBench(config, state_dir=tmp_path):
            frames = _listen(bus, 0.45)
    finally:
        bus.shutdown()
    for node in (config.drive_node, config.sensor_node):
        beats = [f for f in frames if f.cob_id == 0x700 + node]
        assert beats[0].data == bytes([BOOT_UP])
        assert {f.data for f in beats[1:]} == {bytes([PRE_OPERATIONAL])}
        assert 4 <= len(beats) - 1 <= 6
        gaps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(beats[1:])]
        assert statistics.median(gaps) == pytest.approx(0.100, abs=0.025)
    boot_ups = [f.cob_id for f in frames if f.data == bytes([BOOT_UP])]
    assert boot_ups == [0x700 + config.drive_node, 0x700 + config.sensor_node]


def test_heartbeat_reports_the_nmt_state_and_follows_0x1017(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    heartbeat = 0x700 + station.config.drive_node
    station.drive.sdo[0x1017].raw = 20
    station.start_all()
    since = len(station.keeper.frames)
    beats = station.wait_for(heartbeat, 6, since)
    assert {f.data for f in beats} == {bytes([OPERATIONAL])}
    gaps = [b.timestamp - a.timestamp for a, b in itertools.pairwise(beats)]
    assert statistics.median(gaps) == pytest.approx(0.020, abs=0.010)
    station.nmt(0x02, station.config.drive_node)
    since = len(station.keeper.frames)
    assert station.wait_for(heartbeat, 2, since)[-1].data == bytes([STOPPED])


def test_reset_node_reloads_stored_values_and_boots_into_pre_operational(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.drive.sdo
    node = station.config.drive_node
    for sub, value in ((1, -30), (2, 40), (3, 9500), (4, 10500)):
        sdo[0x2100][sub].raw = value
    sdo[0x2101][1].raw = 1_700_000_000
    sdo[0x2101][3].raw = 2
    sdo[0x2102].raw = 64
    sdo[0x1010][1].raw = 0x65766173  # "save"
    for sub, value in ((1, 11), (2, 12), (3, 13000), (4, 7000)):
        sdo[0x2100][sub].raw = value  # not stored
    sdo[0x2103].raw = 300
    station.start_all()
    station.enable()
    sdo[0x60FF].raw = 4000
    station.run(20)
    assert sdo[0x6062].raw > 0

    since = len(station.keeper.frames)
    station.nmt(0x81, node)
    beats = station.wait_for(0x700 + node, 2, since)
    assert [f.data for f in beats] == [bytes([BOOT_UP]), bytes([PRE_OPERATIONAL])]
    assert [sdo[0x2100][sub].raw for sub in (1, 2, 3, 4)] == [-30, 40, 9500, 10500]
    assert sdo[0x2101][1].raw == 1_700_000_000
    assert sdo[0x2101][3].raw == 2
    assert sdo[0x2102].raw == 64
    assert sdo[0x2103].raw == bench.unit.rated_current_mA
    assert sdo[0x60FF].raw == 0
    assert sdo[0x6041].raw == 0x0250
    assert sdo[0x6062].raw == 0
    # The sensor was not reset: it stays OPERATIONAL and alone on the bus after a SYNC.
    assert [f.cob_id for f in station.sync(expect=1)] == [station.tpdo_ids[0]]
    assert bench.drive.effective_trims == (-30, 40, 9500, 10500)


def test_reset_communication_keeps_the_application_but_resets_0x1017(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    node = station.config.drive_node
    sdo[0x2100][1].raw = 33  # not stored: only a reset node would lose it
    sdo[0x1017].raw = 500
    since = len(station.keeper.frames)
    station.nmt(0x82, node)
    beats = station.wait_for(0x700 + node, 2, since)
    assert [f.data for f in beats] == [bytes([BOOT_UP]), bytes([PRE_OPERATIONAL])]
    assert sdo[0x1017].raw == 100
    assert sdo[0x2100][1].raw == 33


def test_broadcast_reset_node_boots_both_devices(bench_station: tuple[SimBench, Station]) -> None:
    bench, station = bench_station
    station.sensor.sdo[0x2000].raw = 8
    since = len(station.keeper.frames)
    station.nmt(0x81, 0)
    for node in (station.config.drive_node, station.config.sensor_node):
        assert station.wait_for(0x700 + node, 1, since)[0].data == bytes([BOOT_UP])
    assert station.sensor.sdo[0x2000].raw == 2  # the range is not persistent
    assert bench.plant.sensor_lsb_mps2() == pytest.approx(2 * 9.80665 / 32768)


def test_nmt_commands_for_another_node_are_ignored(bench_station: tuple[SimBench, Station]) -> None:
    _, station = bench_station
    station.nmt(0x01, 5)
    station.settle()
    station.sync(expect=0)
    station.settle()  # any TPDO of that SYNC would be in before this SDO answer
    assert not [f for f in station.keeper.frames if f.cob_id in station.tpdo_ids]
    station.nmt(0x81, 5)
    station.settle()
    assert not [f for f in station.keeper.frames if f.data == bytes([BOOT_UP])]
