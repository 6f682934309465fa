"""Drive a schedule on any bench: the drive role plus a SYNC clock.

The runner only orchestrates (it owns no maths and no storage): it tells the
drive what each hold needs, lets the clock run the hold's cycles, and always
leaves the drive disabled, whatever happened on the way.
"""

from __future__ import annotations

import logging
from collections.abc import Callable
from dataclasses import dataclass, replace

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


def run_schedule(
    schedule: Schedule,
    drive: Drive,
    clock: SyncClock,
    *,
    on_progress: ProgressCallback | None = None,
) -> None:
    """Run every hold of ``schedule``; the drive ends disabled even on error."""
    total = schedule.cycles
    done = 0
    applied = _Applied()
    log.info(
        "running schedule %s: %d holds, %d SYNC cycles", schedule.name, len(schedule.holds), total
    )
    try:
        if schedule.holds:
            # Amplitude and trims go in before the phases are energised, so the
            # first samples already show the schedule's excitation.
            _apply(drive, replace(schedule.holds[0], velocity=0), applied)
        drive.enable()
        for hold in schedule.holds:
            _apply(drive, hold, applied)
            remaining = hold.cycles
            while remaining > 0:
                step = min(_CHUNK_CYCLES, remaining)
                clock.advance(step)
                remaining -= step
                done += step
                if on_progress is not None:
                    on_progress(done, total, hold)
    except BaseException:
        # The first failure is the one to report; a drive that then also
        # refuses to disable is logged, not allowed to hide it.
        try:
            drive.disable()
        except StationError as exc:
            log.error("could not disable %s after a failure: %s", drive.name, exc)
        raise
    drive.disable()
