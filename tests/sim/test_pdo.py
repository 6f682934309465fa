"""Synchronous TPDOs of the simulated bench: content, order and timing per SYNC."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from fractions import Fraction
from pathlib import Path

import pytest

from station.physics.plant import DriveCommand
from station.sim.bench import SimBench
from tests.sim import Frame, Station, running

# ICD.md §2/§3 byte layouts, written independently of the EDS.
SENSOR_TPDO1 = struct.Struct("<Hhhh")  # counter, X, Y, Z
DRIVE_TPDO1 = struct.Struct("<iHH")  # position demand, amplitude, statusword
DRIVE_TPDO2 = struct.Struct("<hhHH")  # offset A, offset B, gain A, gain B


@pytest.fixture
def bench_station(tmp_path: Path) -> Iterator[tuple[SimBench, Station]]:
    with running(tmp_path / "eeprom") as pair:
        yield pair


class Spy:
    """Wraps the plant's ``advance`` to see what the drive commanded and what came back."""

    def __init__(self, bench: SimBench, monkeypatch: pytest.MonkeyPatch) -> None:
        self.commands: list[DriveCommand] = []
        self.counts: list[tuple[int, int, int]] = []
        real = bench.plant.advance

        def advance(command: DriveCommand) -> tuple[int, int, int]:
            counts = real(command)
            self.commands.append(command)
            self.counts.append(counts)
            return counts

        monkeypatch.setattr(bench.plant, "advance", advance)


def _unpack(frames: list[Frame]) -> tuple[tuple[int, ...], tuple[int, ...], tuple[int, ...]]:
    sensor, drive1, drive2 = frames
    return (
        SENSOR_TPDO1.unpack(sensor.data),
        DRIVE_TPDO1.unpack(drive1.data),
        DRIVE_TPDO2.unpack(drive2.data),
    )


def test_each_sync_brings_one_frame_of_each_tpdo_in_icd_order(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    station.start_all()
    since = len(station.keeper.frames)
    station.run(25)
    station.settle()
    tpdos = [f for f in station.keeper.frames[since:] if f.cob_id in station.tpdo_ids]
    assert [f.cob_id for f in tpdos] == list(station.tpdo_ids) * 25
    assert all(len(f.data) == 8 for f in tpdos)
    assert bench.sync_count == 25


def test_frames_carry_the_plant_samples_and_drive_state_byte_exact(
    bench_station: tuple[SimBench, Station], monkeypatch: pytest.MonkeyPatch
) -> None:
    bench, station = bench_station
    spy = Spy(bench, monkeypatch)
    station.start_all()
    station.drive.sdo[0x2103].raw = 700
    station.enable()
    station.drive.sdo[0x60FF].raw = 2000
    cycles = station.run(40)
    for n, frames in enumerate(cycles):
        sensor, drive1, drive2 = _unpack(frames)
        assert sensor == (n + 1, *spy.counts[n])
        # At rest at SYNC 1 (speed = 0), 200 microsteps/s more per SYNC, target at SYNC 11.
        status = 0x1237 if n == 0 else 0x0237 if n < 10 else 0x0637
        assert drive1[1:] == (700, status)
        assert drive2 == (0, 0, 10000, 10000)
    assert DRIVE_TPDO1.unpack(cycles[-1][1].data)[0] == station.drive.sdo[0x6062].raw
    assert SENSOR_TPDO1.unpack(cycles[-1][0].data)[0] == station.sensor.sdo[0x2010].raw
    assert SENSOR_TPDO1.unpack(cycles[-1][0].data)[1:] == tuple(
        station.sensor.sdo[0x2020][axis].raw for axis in (1, 2, 3)
    )


def test_position_demand_follows_the_exact_ramp_then_slope_velocity_times_period(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    station.start_all()
    station.drive.sdo[0x6083].raw = 150_000
    station.enable()
    station.drive.sdo[0x60FF].raw = 12_800
    positions = [DRIVE_TPDO1.unpack(f[1].data)[0] for f in station.run(150)]
    # Independent model: the target takes effect at SYNC 1, then the velocity steps by 150
    # per period up to 12800, trapezoidal integration over each 1 ms period, position
    # floored to whole microsteps.
    period = Fraction(1, 1000)
    velocity, position, expected = Fraction(0), Fraction(0), [0]
    for _ in range(149):
        new_velocity = min(velocity + 150, Fraction(12_800))
        position += (velocity + new_velocity) / 2 * period
        velocity = new_velocity
        expected.append(position.numerator // position.denominator)
    assert positions == expected
    assert positions[-1] - positions[-11] == 128  # 12800 microsteps/s · 10 ms


def test_trims_change_in_tpdo2_and_at_the_plant_exactly_at_the_next_sync(
    bench_station: tuple[SimBench, Station], monkeypatch: pytest.MonkeyPatch
) -> None:
    bench, station = bench_station
    spy = Spy(bench, monkeypatch)
    station.start_all()
    station.enable()
    before = station.run(3)
    station.drive.sdo[0x2100][1].raw = 25
    station.drive.sdo[0x2100][4].raw = 10100
    station.drive.sdo[0x2103].raw = 600
    assert station.drive.sdo[0x2100][1].raw == 25  # held at once ...
    assert bench.drive.effective_trims == (0, 0, 10000, 10000)  # ... in effect only later
    after = station.run(2)
    assert _unpack(before[-1])[2] == (0, 0, 10000, 10000)
    assert _unpack(after[0])[2] == (25, 0, 10000, 10100)
    assert _unpack(before[-1])[1][1] == bench.unit.rated_current_mA
    assert _unpack(after[0])[1][1] == 600
    # The plant saw the old trims over the period that ended at that SYNC, new ones after.
    assert spy.commands[3].trims.offset_a_mA == 0.0
    assert spy.commands[4].trims.offset_a_mA == 25.0
    assert spy.commands[4].trims.gain_b == 10100.0
    assert spy.commands[4].amplitude_mA == 600.0


def test_disable_de_energises_and_freezes_the_demand_from_the_next_sync(
    bench_station: tuple[SimBench, Station], monkeypatch: pytest.MonkeyPatch
) -> None:
    bench, station = bench_station
    spy = Spy(bench, monkeypatch)
    station.start_all()
    station.enable()
    station.drive.sdo[0x60FF].raw = 5000
    station.run(30)
    station.drive.sdo[0x6040].raw = 0x06
    frames = station.run(5)
    positions = [DRIVE_TPDO1.unpack(f[1].data)[0] for f in frames]
    assert len(set(positions)) == 1
    assert spy.commands[30].enabled  # the period in which the disable arrived
    assert not any(c.enabled for c in spy.commands[31:])
    assert all(c.velocity == 0.0 for c in spy.commands[31:])
    assert DRIVE_TPDO1.unpack(frames[-1][1].data)[2] == 0x0231


def test_only_operational_devices_send_pdos(bench_station: tuple[SimBench, Station]) -> None:
    bench, station = bench_station
    drive_id, sensor_id = station.config.drive_node, station.config.sensor_node
    since = len(station.keeper.frames)
    station.run(3, expect=0)
    station.settle()
    assert not [f for f in station.keeper.frames[since:] if f.cob_id in station.tpdo_ids]
    station.nmt(0x01, drive_id)
    station.settle()
    assert [f.cob_id for f in station.sync(expect=2)] == list(station.tpdo_ids[1:])
    station.nmt(0x01, sensor_id)
    station.nmt(0x02, drive_id)
    station.sensor.sdo.upload(0x1000, 0)
    assert [f.cob_id for f in station.sync(expect=1)] == [station.tpdo_ids[0]]
    station.nmt(0x80)  # broadcast pre-operational
    station.sensor.sdo.upload(0x1000, 0)
    since = len(station.keeper.frames)
    station.run(2, expect=0)
    station.settle()
    assert not [f for f in station.keeper.frames[since:] if f.cob_id in station.tpdo_ids]
    assert bench.sync_count == 7  # the sensor sampled every SYNC nevertheless


def test_sample_counter_wraps_at_65536(bench_station: tuple[SimBench, Station]) -> None:
    bench, station = bench_station
    station.start_all()
    with bench._lock:  # 65534 SYNCs would take half a minute; start near the wrap instead
        bench.sensor.values[(0x2010, 0)] = 65534
    counters = [SENSOR_TPDO1.unpack(f[0].data)[0] for f in station.run(4)]
    assert counters == [65535, 0, 1, 2]


def test_a_tpdo_marked_invalid_in_its_cob_id_is_not_sent(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    station.start_all()
    cob_id = station.drive.sdo[0x1801][1]
    cob_id.raw = 0x8000_0000 | (0x280 + station.config.drive_node)
    assert [f.cob_id for f in station.sync(expect=2)] == list(station.tpdo_ids[:2])
    cob_id.raw = 0x280 + station.config.drive_node
    assert [f.cob_id for f in station.sync()] == list(station.tpdo_ids)


def test_canopen_pdo_configuration_round_trips_against_the_static_mapping(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    drive = station.drive
    # Read 0x1800.., 0x1A00.. over SDO as a station driver would, then write them back:
    # a static mapping must tolerate canopen's save().
    drive.tpdo.read()  # type: ignore[no-untyped-call]
    drive.tpdo.save()  # type: ignore[no-untyped-call]
    assert [(v.index, v.subindex) for v in drive.tpdo[1].map] == [
        (0x6062, 0), (0x2103, 0), (0x6041, 0)
    ]  # fmt: skip
    station.start_all()
    drive.sdo[0x2100][2].raw = -77
    station.run(2)
    station.settle()
    assert drive.tpdo[2].map[1].raw == -77
    assert drive.tpdo[1].map[2].raw == 0x0250
