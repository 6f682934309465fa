"""What a bench file says about a simulated bench: the unit, its sensor and the faults
to inject.

Declarations only, read by the runtime's bench files and acted on by the simulator
(``station.sim``), which the runtime imports only when it opens a simulated bench.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

from station.core import Effect, LoadKind
from station.physics.params import UnitParams


class FaultKind(StrEnum):
    """What goes wrong (bench files name faults by these values)."""

    SDO_TIMEOUT = "sdo_timeout"  # the drive ignores its next ``count`` SDO requests
    DRIVE_SILENT = "drive_silent"  # the drive falls off the bus for good (no heartbeat)
    SENSOR_SILENT = "sensor_silent"  # the sensor node falls off the bus for good
    SENSOR_FRAMES_LOST = "sensor_frames_lost"  # ``count`` sensor TPDOs in a row are lost
    ERROR_FRAMES = "error_frames"  # ``count`` error frames, one per SYNC (bus errors)
    BUS_OFF = "bus_off"  # the station's CAN controller reports bus-off
    EEPROM_FAILURE = "eeprom_failure"  # every later store (0x1010:01) is refused
    POWER_CYCLE = "power_cycle"  # the drive reboots: RAM trims revert to the EEPROM's
    SENSOR_SATURATED = "sensor_saturated"  # every later sample clips at ±32767
    SENSOR_UNPLUGGED = "sensor_unplugged"  # the MEMS element is gone: the node sends zeros


COUNTED_KINDS = frozenset(
    {FaultKind.SDO_TIMEOUT, FaultKind.SENSOR_FRAMES_LOST, FaultKind.ERROR_FRAMES}
)
"""Faults whose ``count`` means something; the others happen once and last."""


@dataclass(frozen=True)
class Fault:
    """One fault: what, from when (simulated seconds after power-on), how many."""

    kind: FaultKind
    at_s: float = 0.0
    count: int = 1

    def __post_init__(self) -> None:
        if not self.at_s >= 0.0:
            raise ValueError(f"{self.kind}: at_s must be >= 0, got {self.at_s}")
        if self.count < 1:
            raise ValueError(f"{self.kind}: count must be >= 1, got {self.count}")

    def at_sync(self, period_s: float) -> int:
        """The SYNC at which the fault is armed (0: before the first SYNC)."""
        return round(self.at_s / period_s)

    def __str__(self) -> str:
        extra = f" x{self.count}" if self.kind in COUNTED_KINDS else ""
        return f"{self.kind.value}{extra} at {self.at_s:g} s"



@dataclass(frozen=True)
class SimSettings:
    """The simulated hardware behind a simulated bench."""

    load: LoadKind = LoadKind.DISK
    unit: str | None = None  # serial on the fixture; None: the unit the operator names
    effects: frozenset[Effect] | None = None  # None: each unit's own concealed effects
    noise_ug: float | None = None  # sensor noise density; None: the unit's own
    seed: int = 0
    faults: tuple[Fault, ...] = ()  # injected, in simulated time since power-on
    # A unit of the wide population (``station.sim.population``) on the fixture instead
    # of the serial's own: calibrated under its own serial, with its own load.
    drawn: UnitParams | None = None
