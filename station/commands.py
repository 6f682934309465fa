"""The station's own log of what it told a drive that reports nothing on the bus.

A Modbus drive has no SYNC-locked TPDOs (ICD.md §4), so the only record of
its state is what the station wrote, and when. ``LoggedDrive`` stands in
front of such a drive and notes, for every set-point write, the SYNC count
before it was sent and after it was acknowledged; the procedure's live
analysis and the recording's metadata both read that ``CommandLog``, so a
Modbus run's recording can be analysed again off the bench like any other.
"""

from __future__ import annotations

import logging
import threading
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from drivers.base import CalibrationRecord, DeviceIdentity, Drive, DriveState
from station.analysis.commanded import (
    DRIVE_COMMANDS_KEY,
    DRIVE_STATE_KEY,
    Commanded,
    CommandTiming,
)
from station.core import Trims
from station.errors import StationError

_log = logging.getLogger(__name__)


class CommandLog:
    """Every state the station put the drive in, stamped in samples (SYNCs seen)."""

    def __init__(self, timing: CommandTiming, samples_seen: Callable[[], int]) -> None:
        self.timing = timing
        self.samples_seen = samples_seen
        self._lock = threading.Lock()
        self._entries: list[Commanded] = []

    def append(self, entry: Commanded) -> None:
        with self._lock:
            self._entries.append(entry)

    def entries(self) -> list[Commanded]:
        with self._lock:
            return list(self._entries)

    def metadata(self) -> dict[str, Any]:
        """The recording metadata keys that let ``station analyze`` rebuild the drive's state."""
        return {DRIVE_STATE_KEY: self.timing.to_json(),
                DRIVE_COMMANDS_KEY: [e.to_json() for e in self.entries()]}


class LoggedDrive(Drive):
    """``inner`` with each set-point write logged; everything else passes through."""

    def __init__(self, inner: Drive, log: CommandLog) -> None:
        self.inner = inner
        self.name = inner.name
        self.log = log
        self._closed = False
        # What the drive holds before the station writes anything: its own trims, at rest.
        self._state = Commanded(sent=0, acknowledged=0, enabled=False, velocity=0,
                                amplitude_mA=0, trims=inner.read_trims().integers())

    def _logged(self, write: Callable[[], None], **changes: Any) -> None:
        sent = self.log.samples_seen()
        write()
        acknowledged = self.log.samples_seen()
        self._state = replace(self._state, sent=sent, acknowledged=acknowledged, **changes)
        self.log.append(self._state)

    # -- the writes that change what the sensor sees ------------------------------------------

    def enable(self) -> None:
        self._logged(self.inner.enable, enabled=True, velocity=0)

    def disable(self) -> None:
        self._logged(self.inner.disable, enabled=False, velocity=0)

    def set_velocity(self, microsteps_per_s: int) -> None:
        self._logged(lambda: self.inner.set_velocity(microsteps_per_s), velocity=microsteps_per_s)

    def set_amplitude(self, amplitude_mA: int) -> None:
        self._logged(lambda: self.inner.set_amplitude(amplitude_mA), amplitude_mA=amplitude_mA)

    def write_trims(self, trims: Trims) -> None:
        self._logged(lambda: self.inner.write_trims(trims), trims=trims.integers())

    def reset(self) -> None:
        # A reset drive is de-energised and holds its stored trims, read back below.
        self._logged(self.inner.reset, enabled=False, velocity=0)
        self._logged(lambda: None, trims=self.inner.read_trims().integers())

    # -- pass-through -------------------------------------------------------------------------

    def identity(self) -> DeviceIdentity:
        return self.inner.identity()

    def rated_current_mA(self) -> int:
        return self.inner.rated_current_mA()

    def microsteps_per_fullstep(self) -> int:
        return self.inner.microsteps_per_fullstep()

    def state(self) -> DriveState:
        return self.inner.state()

    def read_trims(self) -> Trims:
        return self.inner.read_trims()

    def store(self) -> None:
        self.inner.store()

    def read_calibration_record(self) -> CalibrationRecord:
        return self.inner.read_calibration_record()

    def write_calibration_record(self, record: CalibrationRecord) -> None:
        self.inner.write_calibration_record(record)

    @property
    def resettable(self) -> bool:
        return self.inner.resettable

    @property
    def reports_state(self) -> bool:
        return self.inner.reports_state

    def check(self) -> None:
        self.inner.check()

    def close(self) -> None:
        """Disable (logged), once; the bench owns the inner drive's transport and closes it."""
        if self._closed:
            return
        self._closed = True
        try:
            self.disable()
        except StationError as exc:
            _log.warning("%s: could not disable: %s", self.name, exc)
