"""The schedule runner: sends only what changes, always leaves the drive disabled."""

from __future__ import annotations

import pytest

from drivers.base import CalibrationRecord, DeviceIdentity, Drive, DriveState
from drivers.canbus import SyncClock
from station.core import NOMINAL_TRIMS, Trims
from station.errors import DeviceTimeout
from station.runner import run_schedule
from station.schedules import Hold, Phase, Schedule


class RecordingDrive(Drive):
    """Remembers every command; can be told to fail on disable."""

    def __init__(self, fail_disable: bool = False) -> None:
        self.calls: list[tuple[str, object]] = []
        self.fail_disable = fail_disable
        self.enabled = False

    def identity(self) -> DeviceIdentity:
        return DeviceIdentity(1, 2, 3, 123)

    def rated_current_mA(self) -> int:
        return 1000

    def microsteps_per_fullstep(self) -> int:
        return 256

    def state(self) -> DriveState:
        return DriveState.OPERATION_ENABLED if self.enabled else DriveState.SWITCH_ON_DISABLED

    def enable(self) -> None:
        self.calls.append(("enable", None))
        self.enabled = True

    def disable(self) -> None:
        self.calls.append(("disable", None))
        if self.fail_disable:
            raise DeviceTimeout("drive", "no SDO answer")
        self.enabled = False

    def set_velocity(self, microsteps_per_s: int) -> None:
        self.calls.append(("velocity", microsteps_per_s))

    def set_amplitude(self, amplitude_mA: int) -> None:
        self.calls.append(("amplitude", amplitude_mA))

    def write_trims(self, trims: Trims) -> None:
        self.calls.append(("trims", trims))

    def read_trims(self) -> Trims:
        return NOMINAL_TRIMS

    def store(self) -> None:
        self.calls.append(("store", None))

    def reset(self) -> None:
        self.calls.append(("reset", None))

    def read_calibration_record(self) -> CalibrationRecord:
        return CalibrationRecord(0, 0, 0)

    def write_calibration_record(self, record: CalibrationRecord) -> None:
        self.calls.append(("record", record))

    def close(self) -> None:
        self.disable()


class CountingClock(SyncClock):
    def __init__(self, fail_after: int | None = None) -> None:
        self._cycles = 0
        self._fail_after = fail_after

    @property
    def period_s(self) -> float:
        return 0.001

    @property
    def cycles(self) -> int:
        return self._cycles

    def advance(self, cycles: int) -> None:
        if self._fail_after is not None and self._cycles + cycles > self._fail_after:
            raise DeviceTimeout("sensor", "no frame 0x190 for 20 consecutive SYNCs")
        self._cycles += cycles

    def close(self) -> None:
        pass


SHIFTED = Trims(offset_a_mA=-100.0)
SCHEDULE = Schedule(
    "test",
    (
        Hold(Phase.STANDSTILL, 0, 800, NOMINAL_TRIMS, 50),
        Hold(Phase.BASELINE, 20480, 800, NOMINAL_TRIMS, 250),
        Hold(Phase.SWEEP_OFFSET_A, 20480, 800, SHIFTED, 250),
        Hold(Phase.STOP, 0, 800, SHIFTED, 50),
    ),
)


def test_every_cycle_runs_and_only_changes_are_sent() -> None:
    drive, clock = RecordingDrive(), CountingClock()
    progress: list[int] = []
    run_schedule(
        SCHEDULE, drive, clock, on_progress=lambda done, total, hold: progress.append(done)
    )
    assert clock.cycles == SCHEDULE.cycles == progress[-1]
    assert drive.calls == [
        ("amplitude", 800),
        ("trims", NOMINAL_TRIMS),
        ("velocity", 0),
        ("enable", None),
        ("velocity", 20480),
        ("trims", SHIFTED),
        ("velocity", 0),
        ("disable", None),
    ]
    assert not drive.enabled


def test_a_failing_clock_still_leaves_the_drive_disabled() -> None:
    drive = RecordingDrive()
    with pytest.raises(DeviceTimeout, match="0x190"):
        run_schedule(SCHEDULE, drive, CountingClock(fail_after=400))
    assert drive.calls[-1] == ("disable", None)
    assert not drive.enabled


def test_the_first_failure_is_reported_even_when_disable_fails_too() -> None:
    drive = RecordingDrive(fail_disable=True)
    with pytest.raises(DeviceTimeout) as raised:
        run_schedule(SCHEDULE, drive, CountingClock(fail_after=400))
    assert raised.value.device == "sensor"
