"""Where the bench devices' electronic data sheets live, and how to load them.

The station (``RemoteNode``) and the simulated devices (``LocalNode``) both
build their object dictionaries from these files, so both sides agree on
indices, types and PDO mappings by construction.
"""

from __future__ import annotations

from enum import StrEnum
from pathlib import Path

import canopen

EDS_DIR = Path(__file__).resolve().parent / "eds"

PERSISTED = "EEPROM"
"""``StorageLocation`` of the objects that "save" (0x1010:01) persists."""


class DeviceKind(StrEnum):
    """The two kinds of CANopen device on a bench (ICD.md §2 and §3)."""

    DRIVE = "drive"
    SENSOR = "sensor"


_FILES = {
    DeviceKind.DRIVE: "stepper_drive.eds",
    DeviceKind.SENSOR: "mems_sensor.eds",
}


def eds_path(kind: DeviceKind) -> Path:
    return EDS_DIR / _FILES[DeviceKind(kind)]


def load_od(kind: DeviceKind, node_id: int) -> canopen.ObjectDictionary:
    """A fresh object dictionary; ``$NODEID`` entries resolved for ``node_id``."""
    if not 1 <= node_id <= 127:
        raise ValueError(f"CANopen node-ID must be 1..127, got {node_id}")
    return canopen.import_od(str(eds_path(kind)), node_id)
