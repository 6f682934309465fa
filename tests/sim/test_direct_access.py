"""The drive's objects reached without SDO, as the Modbus facade does: SDO's checks and codes."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from canopen.sdo.exceptions import SdoAbortedError

from station.sim.bench import SimBench
from station.sim.devices import Obj, SimDrive
from tests.sim import Station, running

READ_ONLY, RANGE, NO_OBJECT, DEVICE_STATE = 0x06010002, 0x06090030, 0x06020000, 0x08000022


@pytest.fixture
def bench_station(tmp_path: Path) -> Iterator[tuple[SimBench, Station]]:
    with running(tmp_path) as pair:
        yield pair


def _abort(drive: SimDrive, writes: list[tuple[tuple[int, int], int]]) -> int:
    with pytest.raises(SdoAbortedError) as info:
        drive.write_objects(writes)
    return int(info.value.code)


def test_direct_writes_are_refused_with_the_sdo_abort_codes(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, _ = bench_station
    drive = bench.drive
    assert _abort(drive, [(Obj.OFFSET_A, 501)]) == RANGE  # half the rated current, EDS-free
    assert _abort(drive, [(Obj.GAIN_A, 4999)]) == RANGE  # the EDS's range
    assert _abort(drive, [(Obj.OFFSET_A, 1 << 15)]) == RANGE  # not even an I16
    assert _abort(drive, [(Obj.STATUSWORD, 0)]) == READ_ONLY
    assert _abort(drive, [((0x2200, 0), 1)]) == NO_OBJECT
    with pytest.raises(SdoAbortedError) as info:
        drive.read_object((0x2200, 0))
    assert int(info.value.code) == NO_OBJECT
    assert drive.read_objects([Obj.OFFSET_A, Obj.GAIN_A]) == [0, 10000]


def test_what_is_written_directly_is_what_sdo_reads(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    bench.drive.write_object(Obj.OFFSET_B, -40)
    assert station.drive.sdo[0x2100][2].raw == -40
    station.drive.sdo[0x2100][3].raw = 9500
    assert bench.drive.read_object(Obj.GAIN_A) == 9500


def test_a_refused_set_of_writes_leaves_the_drive_as_it_was(
    bench_station: tuple[SimBench, Station],
) -> None:
    bench, station = bench_station
    drive = bench.drive
    before = dict(drive.values)
    # The microsteps are applied, then the rated current below the amplitude is refused.
    assert _abort(drive, [(Obj.MICROSTEPS, 128), (Obj.RATED_CURRENT, 900)]) == DEVICE_STATE
    assert drive.values == before
    assert station.drive.sdo[0x2102].raw == 256
    station.sync(expect=0)  # nothing was left pending to take effect
    assert drive.command.microsteps_per_fullstep == 256
    drive.write_objects([(Obj.MICROSTEPS, 128), (Obj.RATED_CURRENT, 1200)])
    assert drive.read_objects([Obj.MICROSTEPS, Obj.RATED_CURRENT]) == [128, 1200]
