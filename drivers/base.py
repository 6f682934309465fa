"""The roles a bench is made of, independent of transport.

A procedure talks to a ``Drive`` and an ``AccelerationSensor`` and never to a
bus, so a CANopen drive, a Modbus drive or a simulated one behind the virtual
bus are interchangeable. Both roles are context managers: leaving the block,
normally or by an exception, disables the drive; closing twice is harmless.
"""

from __future__ import annotations

import logging
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from types import TracebackType
from typing import ClassVar, TypeVar

import numpy as np
import numpy.typing as npt

from drivers.transports import DriveTraits
from station.core import Trims
from station.errors import DeviceTimeout, InputError

log = logging.getLogger(__name__)
_T = TypeVar("_T")

LIVENESS_TIMEOUT_S = 1.0
"""How long a device may say nothing before it counts as gone: ten of ICD.md's 100 ms
heartbeats. Longer than CiA 301's usual 1.5 periods, because a false alarm scraps a
good unit's run, while a second more of a dead node costs nothing: the drive stops
by itself when it loses communication."""
REQUEST_RETRIES = 2
"""An unanswered request (SDO, Modbus) is sent again this often, and logged. Safe for
every object the station writes: each holds an absolute value (trims, set-points, a
controlword command, the 'save' signature), so repeating a request the device did
act on, whose answer was lost, changes nothing; none is a counter or a toggle."""


def retried(send: Callable[[], _T], *, device: str, what: str,
            unanswered: type[Exception] | tuple[type[Exception], ...]) -> _T:
    """``send()``, sent again up to ``REQUEST_RETRIES`` times (logged) while unanswered.

    Only ``unanswered`` is retried: a refusal is the device's answer, and asking
    again would only hear it again. The last silence is a ``DeviceTimeout``
    naming ``device`` and ``what`` was asked.
    """
    for attempt in range(REQUEST_RETRIES + 1):
        try:
            return send()
        except unanswered as exc:
            if attempt == REQUEST_RETRIES:
                raise DeviceTimeout(device, f"{what}: no answer to {REQUEST_RETRIES + 1} "
                                    f"attempts ({exc})") from exc
            log.warning("%s: %s unanswered, sending it again (retry %d of %d)",
                        device, what, attempt + 1, REQUEST_RETRIES)
    raise AssertionError("unreachable")

class DriveState(Enum):
    """CiA 402 power state machine states, decoded from the statusword."""

    NOT_READY_TO_SWITCH_ON = "not ready to switch on"
    SWITCH_ON_DISABLED = "switch on disabled"
    READY_TO_SWITCH_ON = "ready to switch on"
    SWITCHED_ON = "switched on"
    OPERATION_ENABLED = "operation enabled"
    QUICK_STOP_ACTIVE = "quick stop active"
    FAULT_REACTION_ACTIVE = "fault reaction active"
    FAULT = "fault"


def decode_statusword(statusword: int) -> DriveState:
    """CiA 402 table: state from bits 0-3, 5 and 6 of the statusword."""
    masked = statusword & 0x6F
    if masked & 0x4F == 0x00:
        return DriveState.NOT_READY_TO_SWITCH_ON
    if masked & 0x4F == 0x40:
        return DriveState.SWITCH_ON_DISABLED
    if masked == 0x21:
        return DriveState.READY_TO_SWITCH_ON
    if masked == 0x23:
        return DriveState.SWITCHED_ON
    if masked == 0x27:
        return DriveState.OPERATION_ENABLED
    if masked == 0x07:
        return DriveState.QUICK_STOP_ACTIVE
    if masked & 0x4F == 0x0F:
        return DriveState.FAULT_REACTION_ACTIVE
    if masked & 0x4F == 0x08:
        return DriveState.FAULT
    return DriveState.NOT_READY_TO_SWITCH_ON


@dataclass(frozen=True)
class DeviceIdentity:
    """CiA 301 identity object 0x1018."""

    vendor_id: int
    product_code: int
    revision: int
    serial_number: int


@dataclass(frozen=True)
class CalibrationRecord:
    """Object 0x2101: when, where and how often the unit was calibrated."""

    calibrated_at: int
    station_id: int
    count: int


@dataclass(frozen=True)
class SensorCapture:
    """Samples streamed by the sensor: raw counts with their sample counters.

    ``lost`` counts samples missing between consecutive counters (ICD.md §3:
    the counter advances by one per SYNC, so gaps are losses).
    """

    counter: npt.NDArray[np.uint16]
    counts: npt.NDArray[np.int16]
    lsb_mps2: float
    lost: int

    @property
    def acceleration(self) -> npt.NDArray[np.float64]:
        """Samples in m/s², shape (n, 3) for the X, Y, Z axes."""
        return self.counts.astype(np.float64) * self.lsb_mps2


class Drive(ABC):
    """A stepper drive with trimmable phase currents (ICD.md §2 or §4)."""

    name: str = "drive"
    TRAITS: ClassVar[DriveTraits] = DriveTraits()
    """What the transport gives the station (``drivers.transports``), asked of the
    class before the drive is opened and of the instance while it runs."""

    @abstractmethod
    def identity(self) -> DeviceIdentity: ...

    @abstractmethod
    def rated_current_mA(self) -> int: ...

    @abstractmethod
    def microsteps_per_fullstep(self) -> int: ...

    @abstractmethod
    def state(self) -> DriveState: ...

    @abstractmethod
    def enable(self) -> None:
        """Walk the CiA 402 state machine to operation enabled (profile velocity)."""

    @abstractmethod
    def disable(self) -> None:
        """Stop the motor and de-energise: target velocity 0, then disable voltage."""

    @abstractmethod
    def set_velocity(self, microsteps_per_s: int) -> None: ...

    @abstractmethod
    def set_amplitude(self, amplitude_mA: int) -> None: ...

    @abstractmethod
    def write_trims(self, trims: Trims) -> None:
        """Write the four trims (rounded to the drive's integers); effective at next SYNC."""

    @abstractmethod
    def read_trims(self) -> Trims: ...

    def _stored_form(self, trims: Trims) -> tuple[int, int, int, int]:
        """The integers a write of ``trims`` sends; NaN or infinity refused before any request."""
        raw = (trims.offset_a_mA, trims.offset_b_mA, trims.gain_a, trims.gain_b)
        if not all(math.isfinite(value) for value in raw):
            raise InputError(f"{self.name}: trims must be finite numbers, not {trims}")
        return trims.integers()

    @abstractmethod
    def store(self) -> None:
        """Persist all parameters to EEPROM (CiA 301 0x1010:01 'save')."""

    @abstractmethod
    def reset(self) -> None:
        """Reset the drive (it reloads stored parameters) and wait until it is back."""

    @property
    def resettable(self) -> bool:
        """Whether ``reset`` exists on this transport (ICD.md §4 gives Modbus none)."""
        return self.TRAITS.resettable

    @property
    def reports_state(self) -> bool:
        """Whether the drive streams its state on the CAN bus with every SYNC (TPDOs).

        When it does not (a Modbus drive), recordings and analysis only know the
        drive's state from what the station commanded, and when.
        """
        return self.TRAITS.reports_state

    def check(self) -> None:
        """Raise a station error if the drive left the state the station put it in.

        Drives that stream their statusword need nothing here: the analysis
        sees it. Others are polled.
        """
        return None

    def check_alive(self) -> None:
        """Raise a station error if the drive fell silent or restarted by itself.

        Cheap (no bus request): the clock calls it many times a second while
        it runs, so a dead drive stops the run at once.
        """
        return None

    @abstractmethod
    def read_calibration_record(self) -> CalibrationRecord: ...

    @abstractmethod
    def write_calibration_record(self, record: CalibrationRecord) -> None: ...

    @abstractmethod
    def close(self) -> None:
        """Leave the drive disabled and release the transport; safe to call twice."""

    def __enter__(self) -> Drive:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


class AccelerationSensor(ABC):
    """A MEMS acceleration sensor streaming one sample per SYNC (ICD.md §3)."""

    name: str = "sensor"

    @abstractmethod
    def identity(self) -> DeviceIdentity: ...

    @abstractmethod
    def range_g(self) -> int: ...

    @abstractmethod
    def set_range_g(self, range_g: int) -> None: ...

    @abstractmethod
    def lsb_mps2(self) -> float:
        """Sensitivity read from the device (0x2001), m/s² per LSB."""

    @abstractmethod
    def start_capture(self) -> None:
        """Start keeping streamed samples (previous ones are discarded)."""

    @abstractmethod
    def stop_capture(self) -> SensorCapture:
        """Stop keeping samples and return those kept since ``start_capture``."""

    def check_alive(self) -> None:
        """Raise a station error if the sensor fell silent or restarted (no bus request)."""
        return None

    @abstractmethod
    def close(self) -> None:
        """Release the transport; safe to call twice."""

    def __enter__(self) -> AccelerationSensor:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
