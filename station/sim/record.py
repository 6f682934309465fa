"""``station sim record`` and ``station sim unit``: simulated runs with known truth.

The recording is made the way a real bench makes one: the simulated devices
sit on a virtual CAN bus, the station drives them through its ordinary
drivers and SYNC clock, and the recorder logs what the bus carried. Only the
truth (the unit's concealed parameters and its optimal trims) comes from the
simulator directly, and it goes to a separate file away from the recording so
an analysis cannot peek at it.
"""

from __future__ import annotations

import hashlib
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any, Final

from station import __version__
from station.benches import SIM_SPEC, open_bench
from station.core import SENSOR_RANGES_G, Effect, LoadKind, Trims
from station.errors import DeviceStateError, IdentityMismatch, InputError
from station.paths import sim_state_dir, truth_dir
from station.physics.optimum import optimal_trims
from station.physics.params import UnitParams, derive_unit
from station.physics.truth import unit_truth
from station.recorder import RecordingWriter
from station.recording import log_format_for, metadata_path_for, write_json_atomically
from station.runner import ProgressCallback, run_schedule
from station.schedules import (
    Schedule,
    ScheduleName,
    SweepPlan,
    named_schedule,
)
from station.serials import Serial
from station.sim.eeprom import Eeprom
from station.simsettings import SimSettings

TRUTH_FORMAT: Final = "hsm-truth/1"
SYNC_PERIOD_S: Final = 0.001
OPERATING_POINT: Final = SweepPlan()
"""The calibration operating point; optimal trims are quoted for it."""


@dataclass(frozen=True)
class SimRecordRequest:
    out: Path
    serial: Serial
    schedule: ScheduleName
    effects: frozenset[Effect] | None
    seed: int = 0
    load: LoadKind = LoadKind.DISK
    loss: float = 0.0
    noise_density_ug: float | None = None
    truth: Path | None = None
    range_g: int | None = None
    """Sensor full-scale range; None: the schedule's own choice."""

    @property
    def truth_path(self) -> Path:
        if self.truth is not None:
            return self.truth
        digest = hashlib.sha256(str(self.out.resolve()).encode()).hexdigest()[:10]
        return truth_dir() / f"{self.out.stem}-{digest}.truth.json"

    def validate(self) -> None:
        """Refuse bad output paths before any bus traffic (exit code 2, nothing written)."""
        log_format_for(self.out)
        _check_writable_file(self.out, "output")
        if self.range_g is not None and self.range_g not in SENSOR_RANGES_G:
            raise InputError(f"--range-g must be one of {SENSOR_RANGES_G}, got {self.range_g}")
        if not 0.0 <= self.loss < 1.0:
            raise InputError(f"--loss must be in [0, 1), got {self.loss}")
        truth = self.truth_path
        if truth.resolve().parent == self.out.resolve().parent:
            raise InputError(
                f"truth file {truth} must not sit beside the recording; choose another directory"
            )
        if self.truth is not None:
            _check_writable_file(truth, "truth")


def _check_writable_file(path: Path, what: str) -> None:
    if path.exists() and path.is_dir():
        raise InputError(f"{what} {path} is a directory")
    parent = path.parent
    if not parent.is_dir():
        raise InputError(f"{what} directory {parent} does not exist")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise InputError(f"{what} directory {parent} is not writable")


@dataclass(frozen=True)
class SimRecordResult:
    recording: Path
    metadata: Path
    truth: Path
    serial: str
    schedule: str
    cycles: int
    frames_seen: int
    frames_recorded: int

    def as_dict(self) -> dict[str, Any]:
        return {
            "recording": str(self.recording),
            "truth": str(self.truth),
            "metadata": str(self.metadata),
            "serial": self.serial,
            "schedule": self.schedule,
            "cycles": self.cycles,
            "frames_seen": self.frames_seen,
            "frames_recorded": self.frames_recorded,
        }


def _extra(request: SimRecordRequest, schedule: str) -> dict[str, Any]:
    return {
        "schedule": schedule,
        "bench": "sim",
        "load": request.load.value,
        "station_software": __version__,
        "recorded_at": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def record_simulation(
    request: SimRecordRequest, *, on_progress: ProgressCallback | None = None
) -> SimRecordResult:
    """Run the named schedule on a simulated bench and record it (ICD.md §5)."""
    request.validate()
    schedule = named_schedule(request.schedule, sync_period_s=SYNC_PERIOD_S)
    if request.range_g is not None:
        schedule = replace(schedule, sensor_range_g=request.range_g)
    return _record(request, schedule, on_progress)


def record_schedule(
    request: SimRecordRequest, schedule: Schedule, *, on_progress: ProgressCallback | None = None
) -> SimRecordResult:
    """Record any schedule on a simulated bench (benchmarks and tests use their own).

    Validation comes first, before any bus traffic: bad input writes nothing.
    """
    request.validate()
    return _record(request, schedule, on_progress)


def _record(
    request: SimRecordRequest, schedule: Schedule, on_progress: ProgressCallback | None
) -> SimRecordResult:
    spec = replace(
        SIM_SPEC,
        sync_period_s=SYNC_PERIOD_S,
        sim=SimSettings(
            load=request.load,
            effects=request.effects,
            noise_ug=request.noise_density_ug,
            seed=request.seed,
        ),
    )
    # The same unit the simulated bench mounts (derived from the serial): its truth.
    unit = derive_unit(
        request.serial.label,
        load=request.load,
        effects=request.effects,
        noise_density_ug=request.noise_density_ug,
    )
    with open_bench(spec, request.serial) as session:
        drive, sensor = session.drive, session.sensor
        identity = drive.identity()
        if identity.serial_number != request.serial.number:
            raise IdentityMismatch(
                drive.name,
                f"reports serial {identity.serial_number}, expected {request.serial.number}",
            )
        microsteps = drive.microsteps_per_fullstep()
        if microsteps != schedule.microsteps:
            # Velocities are in microsteps/s: a mismatch would run another speed.
            raise DeviceStateError(
                drive.name,
                f"runs {microsteps} microsteps per full step, the schedule was "
                f"planned for {schedule.microsteps}",
            )
        sensor.set_range_g(schedule.sensor_range_g)
        metadata = session.recording_metadata(
            request.serial.label,
            microsteps=microsteps,
            rotor_teeth=unit.rotor_teeth,
            rated_current_mA=drive.rated_current_mA(),
            extra=_extra(request, schedule.name),
        )
        with RecordingWriter(
            request.out,
            metadata,
            clock=session.recording_clock(),
            loss_probability=request.loss,
            seed=request.seed,
        ) as recorder:
            with session.listening(recorder):
                run_schedule(schedule, drive, session.clock, on_progress=on_progress)
            recorder.commit()
    # Truth is written only for a recording that exists, and never beside it.
    truth = _truth(unit, request, schedule.name, schedule.cycles)
    truth_path = request.truth_path
    truth_path.parent.mkdir(parents=True, exist_ok=True)
    write_json_atomically(truth_path, truth)
    return SimRecordResult(
        recording=request.out,
        metadata=metadata_path_for(request.out),
        truth=truth_path,
        serial=request.serial.label,
        schedule=schedule.name,
        cycles=schedule.cycles,
        frames_seen=recorder.frames_seen,
        frames_recorded=recorder.frames_written,
    )


def operating_optimum(unit: UnitParams) -> Trims:
    """The trims that null ``unit``'s ripple at the operating point: what a truth file
    states, for a recording made by any path (bus or in process)."""
    return optimal_trims(
        unit,
        amplitude_mA=float(OPERATING_POINT.amplitude_mA),
        electrical_hz=OPERATING_POINT.electrical_hz,
        sync_period_s=SYNC_PERIOD_S,
    )


def _truth(
    unit: UnitParams, request: SimRecordRequest, schedule: str, cycles: int
) -> dict[str, Any]:
    return {
        "format": TRUTH_FORMAT,
        "recording": str(request.out.resolve()),
        "serial": request.serial.label,
        "schedule": schedule,
        "cycles": cycles,
        "seed": request.seed,
        "load": request.load.value,
        "frame_loss": request.loss,
        "effects": sorted(e.value for e in unit.effects),
        "operating_point": {
            "amplitude_mA": OPERATING_POINT.amplitude_mA,
            "electrical_hz": OPERATING_POINT.electrical_hz,
        },
        "optimal_trims": operating_optimum(unit).as_dict(),
        "unit": unit_truth(unit),
    }


def describe_unit(
    serial: Serial,
    *,
    load: LoadKind = LoadKind.DISK,
    effects: frozenset[Effect] | None = None,
    amplitude_mA: float = float(OPERATING_POINT.amplitude_mA),
    electrical_hz: float = OPERATING_POINT.electrical_hz,
) -> dict[str, Any]:
    """What ``station sim unit`` reveals: concealed imperfections and optimal trims."""
    unit = derive_unit(serial.label, load=load, effects=effects)
    optimum = optimal_trims(
        unit, amplitude_mA=amplitude_mA, electrical_hz=electrical_hz, sync_period_s=SYNC_PERIOD_S
    )
    truth = unit_truth(unit)
    stored = Eeprom.peek(sim_state_dir(), serial.label)
    return {
        "serial": serial.label,
        "optimal_trims": optimum.as_dict(),
        "effects": truth.get("effects", []),
        "operating_point": {"amplitude_mA": amplitude_mA, "electrical_hz": electrical_hz},
        "load": load.value,
        "stored_trims": stored.as_dict() if stored is not None else None,
        "unit": truth,
    }
