"""The simulated drive's EEPROM file."""

from __future__ import annotations

import json
import os
from pathlib import Path

import pytest

from station.core import Trims
from station.errors import DeviceError
from station.sim.eeprom import FORMAT, Eeprom, file_for

FACTORY = {(0x2100, 1): 0, (0x2100, 2): 0, (0x2100, 3): 10000, (0x2100, 4): 10000,
           (0x2102, 0): 256}  # fmt: skip


def test_a_unit_that_never_stored_loads_its_factory_image(tmp_path: Path) -> None:
    eeprom = Eeprom(file_for(tmp_path, "SN1"), "SN1", FACTORY)
    assert eeprom.image() == FACTORY
    assert Eeprom.peek(tmp_path, "SN1") is None


def test_stored_values_survive_into_a_new_instance_and_peek(tmp_path: Path) -> None:
    path = file_for(tmp_path, "SN1")
    stored = {**FACTORY, (0x2100, 1): -12, (0x2100, 4): 9876}
    Eeprom(path, "SN1", FACTORY).store(stored)
    assert Eeprom(path, "SN1", FACTORY).image() == stored
    assert Eeprom.peek(tmp_path, "SN1") == Trims(-12.0, 0.0, 10000.0, 9876.0)
    document = json.loads(path.read_text())
    assert document["format"] == FORMAT
    assert document["serial"] == "SN1"
    assert document["objects"]["0x2100:01"] == -12


def test_store_replaces_the_file_atomically_and_leaves_no_temporary(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = file_for(tmp_path / "deep" / "dir", "SN1")
    eeprom = Eeprom(path, "SN1", FACTORY)
    eeprom.store(FACTORY)
    before = path.read_text()

    def failing_replace(src: str, dst: str) -> None:
        raise OSError("disk full")

    monkeypatch.setattr(os, "replace", failing_replace)
    with pytest.raises(OSError, match="disk full"):
        eeprom.store({**FACTORY, (0x2100, 1): 5})
    assert path.read_text() == before
    assert sorted(p.name for p in path.parent.iterdir()) == [path.name]
    assert eeprom.image() == FACTORY  # the failed store did not pretend to succeed


def test_store_needs_every_persistent_object(tmp_path: Path) -> None:
    eeprom = Eeprom(file_for(tmp_path, "SN1"), "SN1", FACTORY)
    with pytest.raises(ValueError, match="missing"):
        eeprom.store({(0x2100, 1): 3})


def test_erase_brings_back_the_factory_image(tmp_path: Path) -> None:
    path = file_for(tmp_path, "SN1")
    eeprom = Eeprom(path, "SN1", FACTORY)
    eeprom.store({**FACTORY, (0x2102, 0): 16})
    eeprom.erase()
    assert not path.exists()
    assert Eeprom(path, "SN1", FACTORY).image() == FACTORY


@pytest.mark.parametrize(
    ("document", "reason"),
    [
        ("not json", "unreadable"),
        (json.dumps({"format": "other/1", "serial": "SN1", "objects": {}}), "format"),
        (json.dumps({"format": FORMAT, "serial": "SN2", "objects": {}}), "belongs to 'SN2'"),
        (json.dumps({"format": FORMAT, "serial": "SN1", "objects": {"0x2100:01": 1.5}}),
         "not an integer"),
        (json.dumps({"format": FORMAT, "serial": "SN1", "objects": {"2100sub1": 1}}), "0xIIII"),
        (json.dumps({"format": FORMAT, "serial": "SN1", "objects": {"0x2103:00": 1}}),
         "not persistent"),
    ],
)
def test_a_damaged_image_is_reported_not_silently_replaced(
    tmp_path: Path, document: str, reason: str
) -> None:
    path = file_for(tmp_path, "SN1")
    path.write_text(document)
    with pytest.raises(DeviceError, match=reason):
        Eeprom(path, "SN1", FACTORY)
