"""What a unit keeps across resets and across benches (processes): its EEPROM."""

from __future__ import annotations

import json
from pathlib import Path

from station.core import Trims
from station.paths import sim_state_dir
from station.sim.bench import SimBench
from station.sim.eeprom import Eeprom
from tests.sim import running, unique_config

SAVE, LOAD = 0x65766173, 0x64616F6C


def _trims(station_sdo: object) -> list[int]:
    return [int(station_sdo[0x2100][sub].raw) for sub in (1, 2, 3, 4)]  # type: ignore[index]


def test_stored_trims_survive_into_a_new_bench_for_the_same_serial(tmp_path: Path) -> None:
    with running(tmp_path, serial="SN77") as (_, station):
        sdo = station.drive.sdo
        for sub, value in ((1, 17), (2, -23), (3, 10250), (4, 9750)):
            sdo[0x2100][sub].raw = value
        sdo[0x2101][2].raw = 42
        sdo[0x1010][1].raw = SAVE
        sdo[0x2100][1].raw = 99  # after the store: lost with the bench
    with running(tmp_path, serial="SN77") as (bench, station):
        assert _trims(station.drive.sdo) == [17, -23, 10250, 9750]
        assert station.drive.sdo[0x2101][2].raw == 42
        assert bench.drive.effective_trims == (17, -23, 10250, 9750)
    assert Eeprom.peek(tmp_path, "SN77") == Trims(17.0, -23.0, 10250.0, 9750.0)
    document = json.loads((tmp_path / "SN77.json").read_text())
    assert document["objects"]["0x2100:02"] == -23
    assert document["objects"]["0x6075:00"] == bench.unit.rated_current_mA


def test_unstored_trims_are_lost_in_a_new_bench(tmp_path: Path) -> None:
    with running(tmp_path, serial="SN78") as (_, station):
        station.drive.sdo[0x2100][1].raw = 55
    with running(tmp_path, serial="SN78") as (_, station):
        assert _trims(station.drive.sdo) == [0, 0, 10000, 10000]
    assert not (tmp_path / "SN78.json").exists()


def test_another_serial_does_not_see_the_stored_image(tmp_path: Path) -> None:
    with running(tmp_path, serial="SN1") as (_, station):
        station.drive.sdo[0x2100][2].raw = 5
        station.drive.sdo[0x1010][1].raw = SAVE
    with running(tmp_path, serial="SN2") as (_, station):
        assert _trims(station.drive.sdo) == [0, 0, 10000, 10000]


def test_restore_defaults_takes_effect_at_the_next_reset_only(tmp_path: Path) -> None:
    with running(tmp_path, serial="SN79") as (_, station):
        sdo = station.drive.sdo
        sdo[0x2100][1].raw = 12
        sdo[0x2102].raw = 32
        sdo[0x1010][1].raw = SAVE
        sdo[0x1011][1].raw = LOAD
        assert sdo[0x2100][1].raw == 12  # nothing changes before the reset
        since = len(station.keeper.frames)
        station.nmt(0x81, station.config.drive_node)
        station.wait_for(0x701, 1, since)
        assert _trims(sdo) == [0, 0, 10000, 10000]
    with running(tmp_path, serial="SN79") as (bench, station):
        assert station.drive.sdo[0x2102].raw == bench.unit.microsteps


def test_the_default_state_directory_is_under_station_home(station_home: Path) -> None:
    config = unique_config(serial="SN80")
    with SimBench(config) as bench:
        assert bench.drive.eeprom.path == sim_state_dir() / "SN80.json"
        assert station_home in bench.drive.eeprom.path.parents
