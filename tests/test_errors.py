"""Station errors keep their message, device and device code across processes."""

from __future__ import annotations

import pickle

from station.errors import DatabaseError, DeviceTimeout, ModbusException, SdoAbort, StationError
from station.recipes import RecipeError


def _round_trip(error: StationError) -> StationError:
    again = pickle.loads(pickle.dumps(error))  # what a worker process hands back
    assert type(again) is type(error)
    assert str(again) == str(error)
    assert again.exit_code == error.exit_code
    return again


def test_device_errors_keep_the_device_and_its_own_code_across_processes() -> None:
    timeout = _round_trip(DeviceTimeout("sensor", "no frame 0x190"))
    assert isinstance(timeout, DeviceTimeout) and timeout.device == "sensor"
    abort = _round_trip(SdoAbort("drive", 0x1010, 1, 0x08000020))
    assert isinstance(abort, SdoAbort)
    assert (abort.index, abort.subindex, abort.code) == (0x1010, 1, 0x08000020)
    modbus = _round_trip(ModbusException("drive", 6, 0x0100, 2, "illegal data address"))
    assert isinstance(modbus, ModbusException) and modbus.code == 2


def test_recipe_and_database_errors_cross_processes_with_every_problem() -> None:
    recipe = _round_trip(RecipeError("spin3.toml", ["name: 'default'", "motion: x"]))
    assert isinstance(recipe, RecipeError) and recipe.problems == ("name: 'default'", "motion: x")
    database = _round_trip(DatabaseError("/tmp/x.db", "locked"))
    assert isinstance(database, DatabaseError) and database.database == "/tmp/x.db"
