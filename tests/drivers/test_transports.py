"""The transport registry: each transport's driver, imported when used, says what the
drive reports; the station asks it, not the transport's name."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path
from types import ModuleType

import pytest

from drivers import transports
from drivers.base import Drive
from drivers.canopen_drive import CanopenDrive
from drivers.modbus_drive import ModbusDrive
from drivers.transports import DriveTraits, Transport, drive_class, drive_traits
from station import service
from station.benches import SIM_MODBUS_SPEC, SIM_SPEC, BenchSpec
from station.errors import InputError
from station.service import Station, calibrate

ROOT = Path(__file__).parents[2]


def test_every_transport_names_a_drive_class_that_says_what_it_reports() -> None:
    assert set(Transport) == set(transports._DRIVERS)
    assert drive_class(Transport.CANOPEN) is CanopenDrive
    assert drive_class(Transport.MODBUS) is ModbusDrive
    for transport in Transport:
        assert issubclass(drive_class(transport), Drive)
    assert drive_traits(Transport.CANOPEN) == DriveTraits(reports_state=True, resettable=True)
    assert drive_traits(Transport.MODBUS) == DriveTraits(reports_state=False, resettable=False)


def test_a_canopen_line_never_imports_the_modbus_stack() -> None:
    code = ("import sys\n"
            "from drivers.transports import Transport, drive_traits\n"
            "assert drive_traits(Transport.CANOPEN).reports_state\n"
            "print(sorted(m for m in sys.modules if m.split('.')[0] == 'pymodbus'))\n")
    out = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                         text=True, check=True, timeout=120)
    assert out.stdout.strip() == "[]"


def test_whether_the_station_sees_the_drive_angle_is_the_driver_s_answer(
    monkeypatch: pytest.MonkeyPatch, tmp_path: Path,
) -> None:
    assert SIM_SPEC.sees_drive_angle and not SIM_MODBUS_SPEC.sees_drive_angle
    # A CANopen drive whose driver said it reports nothing would be treated as one.
    quiet = ModuleType("quiet_drive")

    class QuietDrive(CanopenDrive):
        TRAITS = DriveTraits(reports_state=False, resettable=True)

    quiet.QuietDrive = QuietDrive  # type: ignore[attr-defined]
    monkeypatch.setitem(sys.modules, "quiet_drive", quiet)
    monkeypatch.setitem(transports._DRIVERS, Transport.CANOPEN, "quiet_drive:QuietDrive")
    spec: BenchSpec = SIM_SPEC
    assert spec.transport is Transport.CANOPEN and not spec.sees_drive_angle
    # ... and a recipe that needs the angle refused before any bus is opened.
    text = (ROOT / "recipes" / "default.toml").read_text(encoding="utf-8")
    recipe = tmp_path / "angle.toml"
    recipe.write_text(text[: text.index("[magnitude_sweep]")].replace(
        'name = "default"', 'name = "angle"'), encoding="utf-8")
    monkeypatch.setattr(service, "unit_on_bench", _no_bench)
    with pytest.raises(InputError, match="magnitude_sweep"):
        calibrate(Station(tmp_path / "station.db", spec, "op"), "SN123", str(recipe))


def _no_bench(*_args: object, **_kwargs: object) -> None:
    raise AssertionError("the bench was opened")
