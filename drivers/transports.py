"""Which driver reaches a drive over each transport, and what such a drive can report.

A bench names its drive's transport; the station asks the transport's driver class, not
the transport's name, what the drive gives it, so that whether the phasors have the
drive's electrical angle is decided here, once, and a new transport is a driver module
and one line below. Drivers are imported only when a bench uses them, the way
python-can imports an interface's module only when it is named: a CANopen line never
loads pymodbus.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING, Final

if TYPE_CHECKING:
    from drivers.base import Drive


class Transport(StrEnum):
    """How the station reaches the drive (CLI.md: CANopen or Modbus)."""

    CANOPEN = "canopen"
    MODBUS = "modbus"


@dataclass(frozen=True)
class DriveTraits:
    """What a drive on one transport gives the station, known before it is opened.

    ``reports_state``: its statusword and position demand come on the CAN bus with every
    SYNC (ICD.md §2), so every sample has the drive's electrical angle and the phasors a
    common reference; a drive without (ICD.md §4, Modbus) is known only by what the
    station commanded, when, and the phase-coherent method cannot run on it.
    ``resettable``: it can be reset to reload its EEPROM, so stored trims are confirmed
    from the EEPROM rather than from RAM.
    """

    reports_state: bool = True
    resettable: bool = True


_DRIVERS: Final[dict[Transport, str]] = {
    Transport.CANOPEN: "drivers.canopen_drive:CanopenDrive",
    Transport.MODBUS: "drivers.modbus_drive:ModbusDrive",
}
"""Each transport's driver, as module:class, imported on first use."""


def drive_class(transport: Transport) -> type[Drive]:
    """The driver class of ``transport`` (its module imported now, once)."""
    module, _, name = _DRIVERS[transport].partition(":")
    found: type[Drive] = getattr(importlib.import_module(module), name)
    return found


def drive_traits(transport: Transport) -> DriveTraits:
    """What a drive reached over ``transport`` reports: its driver's ``TRAITS``."""
    return drive_class(transport).TRAITS
