"""Drive a schedule on any bench: the drive role plus a SYNC clock.

The runner only orchestrates (it owns no maths and no storage): it tells the
drive what each hold needs, lets the clock run the hold's cycles, and always
leaves the drive disabled, whatever happened on the way.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from types import TracebackType

from drivers.base import Drive
from drivers.canbus import SyncClock
from station.core import Trims
from station.errors import StationError
from station.schedules import Hold, Schedule

log = logging.getLogger(__name__)

ProgressCallback = Callable[[int, int, Hold], None]
"""Called with (cycles done, cycles in total, hold being run)."""

_CHUNK_CYCLES = 100


@dataclass
class _Applied:
    velocity: int | None = None
    amplitude_mA: int | None = None
    trims: Trims | None = None


def _apply(drive: Drive, hold: Hold, applied: _Applied) -> None:
    """Send only what changes: every SDO costs bus time on a real bench."""
    if hold.amplitude_mA != applied.amplitude_mA:
        drive.set_amplitude(hold.amplitude_mA)
        applied.amplitude_mA = hold.amplitude_mA
    if hold.trims != applied.trims:
        drive.write_trims(hold.trims)
        applied.trims = hold.trims
    if hold.velocity != applied.velocity:
        drive.set_velocity(hold.velocity)
        applied.velocity = hold.velocity


class Motion:
    """The drive energised across several batches of holds, disabled on leaving.

    A closed-loop calibration decides its next holds from the last ones, so it
    cannot hand the runner one schedule up front; keeping the drive enabled
    between batches also keeps the motor at speed (no ramp, no re-settling)
    while the station computes. Leaving the block disables the drive, and a
    failure to disable after another failure is logged rather than allowed to
    hide the first one.
    """

    def __init__(
        self, drive: Drive, clock: SyncClock, *, on_progress: ProgressCallback | None = None
    ) -> None:
        self._drive = drive
        self._clock = clock
        self._on_progress = on_progress
        self._applied = _Applied()
        self._enabled = False

    def run(self, holds: Sequence[Hold]) -> None:
        """Run ``holds`` in order; progress counts cycles within this batch."""
        total = sum(h.cycles for h in holds)
        done = 0
        if not self._enabled and holds:
            # Amplitude and trims go in before the phases are energised, so the
            # first samples already show the schedule's excitation.
            _apply(self._drive, replace(holds[0], velocity=0), self._applied)
            self._drive.enable()
            self._enabled = True
        for hold in holds:
            _apply(self._drive, hold, self._applied)
            remaining = hold.cycles
            while remaining > 0:
                step = min(_CHUNK_CYCLES, remaining)
                self._clock.advance(step)
                remaining -= step
                done += step
                if self._on_progress is not None:
                    self._on_progress(done, total, hold)
            # A drive polled rather than streaming its state must still be running as told,
            # or the hold just run measured something else.
            self._drive.check()

    def stop(self) -> None:
        """Disable the drive now; the next ``run`` enables it again from standstill."""
        self._enabled = False
        self._applied = _Applied()
        self._drive.disable()

    def __enter__(self) -> Motion:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        if exc is None:
            self.stop()
            return
        try:
            self.stop()
        except StationError as failure:
            log.error("could not disable %s after a failure: %s", self._drive.name, failure)


def run_schedule(
    schedule: Schedule,
    drive: Drive,
    clock: SyncClock,
    *,
    on_progress: ProgressCallback | None = None,
) -> None:
    """Run every hold of ``schedule``; the drive ends disabled even on error."""
    log.info(
        "running schedule %s: %d holds, %d SYNC cycles",
        schedule.name,
        len(schedule.holds),
        schedule.cycles,
    )
    # One batch: the Motion's progress is the schedule's.
    with Motion(drive, clock, on_progress=on_progress) as motion:
        motion.run(schedule.holds)
