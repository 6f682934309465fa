"""SDO service of the simulated devices: round trips, aborts, the CiA 402 state machine."""

from __future__ import annotations

import struct
from collections.abc import Iterator
from pathlib import Path

import pytest
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.base import DriveState, decode_statusword
from station.sim.bench import SimBench
from station.sim.devices import FaultCode
from tests.sim import Station, running

READ_ONLY, RANGE, NO_OBJECT, NO_SUB = 0x06010002, 0x06090030, 0x06020000, 0x06090011
CANNOT_STORE, DEVICE_STATE = 0x08000020, 0x08000022


@pytest.fixture
def bench_station(tmp_path: Path) -> Iterator[tuple[SimBench, Station]]:
    with running(tmp_path / "eeprom") as pair:
        yield pair


def _abort(call: object) -> int:
    assert callable(call)
    with pytest.raises(SdoAbortedError) as info:
        call()
    return int(info.value.code)


def test_identity_and_fixed_objects_read_as_the_icd_says(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.drive.sdo
    assert sdo[0x1000].raw == 0x00030192
    assert sdo[0x1018][4].raw == bench.unit.serial_number
    assert sdo[0x1018][1].raw == 0x00005354
    assert sdo[0x1010][1].raw == 1
    assert sdo[0x1011][1].raw == 1
    assert sdo[0x6075].raw == bench.unit.rated_current_mA
    assert sdo[0x2102].raw == bench.unit.microsteps
    assert sdo[0x2103].raw == bench.unit.rated_current_mA  # powers up at the rated current
    assert sdo[0x6041].raw == 0x0250
    assert sdo[0x6060].raw == 3
    assert sdo[0x6061].raw == 3
    assert sdo[0x6062].raw == 0
    assert sdo[0x606B].raw == 0
    assert sdo[0x1006].raw == 1000
    assert station.sensor.sdo[0x2000].raw == 2
    assert station.sensor.sdo[0x2010].raw == 0


def test_every_writable_drive_object_reads_back_what_was_written(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    written = {
        (0x2100, 1): -100, (0x2100, 2): 120, (0x2100, 3): 9000, (0x2100, 4): 11000,
        (0x2101, 1): 1_700_000_000, (0x2101, 2): 7, (0x2101, 3): 3, (0x2102, 0): 128,
        (0x2103, 0): 400, (0x6060, 0): 3, (0x60FF, 0): -5000, (0x6083, 0): 100_000,
        (0x6084, 0): 150_000, (0x6040, 0): 0x0006, (0x1006, 0): 2000, (0x1019, 0): 0,
    }  # fmt: skip
    for (index, sub), value in written.items():
        (sdo[index][sub] if sub else sdo[index]).raw = value
    for (index, sub), value in written.items():
        assert (sdo[index][sub] if sub else sdo[index]).raw == value, hex(index)


def test_sensor_range_sets_the_sensitivity_of_0x2001(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.sensor.sdo
    for range_g in (2, 4, 8, 16):
        sdo[0x2000].raw = range_g
        assert sdo[0x2000].raw == range_g
        expected = range_g * 9.80665 / 32768
        assert sdo[0x2001].raw == pytest.approx(expected, rel=1e-6)
        assert bench.plant.sensor_lsb_mps2() == pytest.approx(expected)
    assert [sdo[0x2020][axis].raw for axis in (1, 2, 3)] == [0, 0, 0]
    assert sdo[0x1018][4].raw == 1


def test_segmented_transfers_work_both_ways(bench_station: tuple[SimBench, Station]) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    assert sdo[0x1008].raw == "HSM stepper drive with current trims"  # 36 bytes: segmented
    sdo.download(0x2100, 1, struct.pack("<h", -42), force_segment=True)
    assert sdo[0x2100][1].raw == -42


@pytest.mark.parametrize(
    ("index", "sub", "value"),
    [
        (0x2100, 1, 501), (0x2100, 1, -501), (0x2100, 2, 501), (0x2100, 3, 4999),
        (0x2100, 4, 15001), (0x2103, 0, 1001), (0x6060, 0, 1), (0x2102, 0, 0),
        (0x2102, 0, 512), (0x1019, 0, 1), (0x6083, 0, 0), (0x1801, 1, 0x282),
    ],
)  # fmt: skip
def test_out_of_range_value_is_refused_with_abort_0x06090030_and_nothing_changes(
    bench_station: tuple[SimBench, Station], index: int, sub: int, value: int
) -> None:
    bench, station = bench_station
    assert bench.unit.rated_current_mA == 1000  # the ranges above are ±500 mA and ≤ 1000 mA
    var = station.drive.sdo[index][sub] if sub else station.drive.sdo[index]
    before = var.raw
    assert _abort(lambda: setattr(var, "raw", value)) == RANGE
    assert var.raw == before


def test_offset_range_follows_the_rated_current(bench_station: tuple[SimBench, Station]) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    sdo[0x2103].raw = 500
    sdo[0x6075].raw = 1600
    sdo[0x2100][1].raw = 800
    assert sdo[0x2100][1].raw == 800
    # Lowering the rated current below what is held would put the offset out of range.
    assert _abort(lambda: setattr(sdo[0x6075], "raw", 1500)) == DEVICE_STATE
    assert sdo[0x6075].raw == 1600


def test_sensor_range_other_than_2_4_8_16_is_refused(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.sensor.sdo
    for bad in (3, 1, 32):
        assert _abort(lambda bad=bad: setattr(sdo[0x2000], "raw", bad)) == RANGE
    assert sdo[0x2000].raw == 2
    assert bench.plant.sensor_lsb_mps2() == pytest.approx(2 * 9.80665 / 32768)


def test_writing_a_read_only_object_is_refused_with_0x06010002(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    for index, sub in ((0x6041, 0), (0x1018, 4), (0x6062, 0), (0x1000, 0), (0x1008, 0)):
        assert _abort(lambda i=index, s=sub: sdo.download(i, s, b"\x00\x00")) == READ_ONLY
    assert _abort(lambda: station.sensor.sdo.download(0x2010, 0, b"\x05\x00")) == READ_ONLY
    assert sdo[0x6041].raw == 0x0250


def test_unknown_objects_are_refused_with_their_cia301_codes(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    assert _abort(lambda: sdo.upload(0x2200, 0)) == NO_OBJECT
    assert _abort(lambda: sdo.download(0x2200, 0, b"\x01")) == NO_OBJECT
    assert _abort(lambda: sdo.upload(0x2100, 9)) == NO_SUB


def test_store_and_restore_refuse_a_wrong_signature_with_0x08000020(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.drive.sdo
    assert _abort(lambda: setattr(sdo[0x1010][1], "raw", 0x12345678)) == CANNOT_STORE
    assert _abort(lambda: setattr(sdo[0x1011][1], "raw", 0x65766173)) == CANNOT_STORE
    assert not bench.drive.eeprom.path.exists()


def test_microsteps_cannot_change_under_a_running_motor(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    station.enable()
    assert _abort(lambda: setattr(sdo[0x2102], "raw", 128)) == DEVICE_STATE
    sdo[0x6040].raw = 0x07
    sdo[0x2102].raw = 128
    assert sdo[0x2102].raw == 128
    sdo[0x2102].raw = 200  # not a power of two: real drives use such resolutions
    assert sdo[0x2102].raw == 200


def test_statusword_follows_the_cia402_sequence(bench_station: tuple[SimBench, Station]) -> None:
    _, station = bench_station
    sdo = station.drive.sdo

    def command(controlword: int) -> int:
        sdo[0x6040].raw = controlword
        return int(sdo[0x6041].raw)

    assert sdo[0x6041].raw == 0x0250
    assert command(0x06) == 0x0231
    assert command(0x07) == 0x0233
    # Operation enabled, at standstill: target (0) reached and speed = 0 (pv mode).
    assert command(0x0F) == 0x1637
    sdo[0x60FF].raw = 1000
    assert sdo[0x6041].raw == 0x1237  # the new target is not reached yet
    assert command(0x07) == 0x0233  # disable operation
    assert sdo[0x60FF].raw == 0  # the target velocity is dropped on leaving operation enabled
    assert command(0x0F) == 0x1637
    assert command(0x06) == 0x0231  # shutdown from operation enabled
    assert command(0x0F) == 0x1637  # switch on + enable operation from ready to switch on
    assert decode_statusword(command(0x02)) is DriveState.SWITCH_ON_DISABLED  # quick stop
    assert command(0x06) == 0x0231
    assert command(0x00) == 0x0250  # disable voltage
    assert command(0x0F) == 0x0250  # enable operation is not a transition from here


def test_a_fault_sends_emcy_and_only_a_fault_reset_edge_clears_it(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    sdo = station.drive.sdo
    station.enable()
    since = len(station.keeper.frames)
    bench.drive.trip(FaultCode.OVERCURRENT)
    emcy = station.wait_for(0x081, 1, since)
    assert emcy[0].data == struct.pack("<HB5x", 0x2310, 0x03)
    assert sdo[0x6041].raw == 0x0218
    assert decode_statusword(int(sdo[0x6041].raw)) is DriveState.FAULT
    assert sdo[0x1001].raw == 0x03
    sdo[0x6040].raw = 0x06  # ignored in fault
    assert sdo[0x6041].raw == 0x0218
    sdo[0x6040].raw = 0x86  # rising edge of bit 7
    assert sdo[0x6041].raw == 0x0250
    assert sdo[0x1001].raw == 0
    assert station.wait_for(0x081, 2, since)[1].data == bytes(8)


def test_sdo_falls_silent_in_stopped_and_answers_again_in_pre_operational(
    bench_station: tuple[SimBench, Station],
) -> None:
    _, station = bench_station
    sdo = station.drive.sdo
    sdo.RESPONSE_TIMEOUT = 0.1
    station.nmt(0x02, station.config.drive_node)
    with pytest.raises(SdoCommunicationError):
        sdo.upload(0x1000, 0)
    station.nmt(0x80, station.config.drive_node)
    assert sdo[0x1000].raw == 0x00030192
    assert station.sensor.sdo[0x1000].raw == 0x00000194  # the sensor was never stopped
