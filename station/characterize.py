"""``station characterize`` and ``station diagnose``: orchestration only.

Characterization runs the schedule that makes the effects separable on the
station's bench, records it like any run (ICD.md §5, beside the database,
one folder per unit) and diagnoses the recording; diagnosing a recording from
anywhere is the same second half. The maths lives in ``station.diagnosis``.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from station import __version__
from station.analysis.reader import read_recording
from station.benches import open_bench
from station.diagnosis.diagnose import diagnose
from station.diagnosis.results import Diagnosis
from station.errors import DeviceStateError, InputError
from station.procedure import check_identity
from station.recipes import DEFAULT_RECIPE, load_recipe
from station.recorder import RecordingWriter
from station.runner import ProgressCallback, run_schedule
from station.schedules import CharacterizationPlan, characterization_schedule
from station.serials import parse_serial
from station.service import RECORDING_SUFFIX, Station, recordings_dir

log = logging.getLogger(__name__)

REPORT_SUFFIX = ".diagnosis.html"

WORKERS_ENV = "STATION_DIAGNOSIS_WORKERS"
"""How many processes fit a diagnosis's models side by side (default: the CPUs this
process may run on, at most ``MOST_WORKERS``); 1 fits them all in this process."""
MOST_WORKERS = 4
"""A step of the search has about ten models to fit: more workers mostly wait."""


def diagnosis_workers() -> int:
    raw = os.environ.get(WORKERS_ENV)
    if raw:
        try:
            return max(1, int(raw))
        except ValueError:
            raise InputError(f"{WORKERS_ENV}={raw!r} is not a number of processes") from None
    # The CPUs this process may run on where the system says (Linux), else all of them.
    usable = (len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity")
              else os.cpu_count() or 1)
    return max(1, min(MOST_WORKERS, usable))


@dataclass(frozen=True)
class DiagnosisResult:
    """A diagnosis, where its recording came from and where its report went."""

    recording: Path
    diagnosis: Diagnosis
    report: Path | None

    def as_dict(self) -> dict[str, Any]:
        doc = {"recording": str(self.recording), **self.diagnosis.to_dict()}
        doc["report"] = str(self.report) if self.report is not None else None
        doc["serial"] = self.diagnosis.observations.metadata.serial
        return doc


def report_path_for(recording: Path) -> Path:
    return recording.with_name(recording.stem + REPORT_SUFFIX)


def diagnose_recording(recording: Path, *, report: Path | None = None, write_report: bool = True,
                       progress: Callable[[str], None] | None = None,
                       workers: int | None = None) -> DiagnosisResult:
    """Diagnose one recording; the HTML report goes beside it unless told otherwise.
    ``workers``: processes fitting side by side (default ``diagnosis_workers()``)."""
    timeline = read_recording(recording)
    result = diagnose(timeline, progress, diagnosis_workers() if workers is None else workers)
    target: Path | None = None
    if write_report:
        # Imported here: matplotlib costs a second of start-up that --no-report saves.
        from station.diagnosis.report import write_report as write_html  # noqa: PLC0415

        target = report if report is not None else report_path_for(recording)
        write_html(result, target, source=str(recording))
    return DiagnosisResult(recording, result, target)


def characterize(station: Station, serial_label: str, *, recipe_name: str | None = None,
                 plan: CharacterizationPlan | None = None,
                 on_progress: ProgressCallback | None = None,
                 on_step: Callable[[str], None] | None = None,
                 write_report: bool = True) -> DiagnosisResult:
    """Run the characterization schedule around the unit's own trims, record, diagnose.

    The drive's trims are only changed in RAM during the run (never stored) and
    the schedule ends on the trims the drive had, so a characterized unit leaves
    the bench as it came, disabled.
    """
    serial = parse_serial(serial_label)
    # The recipe names the product (rotor teeth, rating); read before any bus traffic.
    product = load_recipe(recipe_name or DEFAULT_RECIPE).product
    chosen = plan or CharacterizationPlan()
    folder = recordings_dir(station.db_path) / serial.label
    stamp = datetime.now(UTC).strftime("%Y%m%dT%H%M%SZ")
    recording = folder / f"{serial.label}-characterization-{stamp}{RECORDING_SUFFIX}"
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create {folder}: {exc.strerror}") from exc
    spec = station.bench
    with open_bench(spec, serial) as session:
        drive, sensor = session.drive, session.sensor
        if on_step is not None:
            on_step("checking identity")
        check_identity(drive, serial)
        microsteps = drive.microsteps_per_fullstep()
        center = drive.read_trims()
        schedule = characterization_schedule(
            chosen, microsteps=microsteps, sync_period_s=spec.sync_period_s, center=center
        )
        rated = drive.rated_current_mA()
        if max(chosen.amplitudes_mA) > rated:
            raise DeviceStateError(
                drive.name, f"rated {rated} mA, below the plan's {max(chosen.amplitudes_mA)} mA"
            )
        sensor.set_range_g(schedule.sensor_range_g)
        metadata = session.recording_metadata(
            serial.label,
            microsteps=microsteps,
            rotor_teeth=product.rotor_teeth,
            rated_current_mA=rated,
            extra={
                "schedule": schedule.name,
                "bench": spec.name,
                "station_id": spec.station_id,
                "operator": station.operator,
                "station_software": __version__,
                "recorded_at": stamp,
                "center_trims": center.as_dict(),
            },
        )
        if on_step is not None:
            on_step(f"running {len(schedule.holds)} holds around {center.as_dict()}")
        with RecordingWriter(recording, metadata, clock=session.recording_clock()) as recorder:
            with session.listening(recorder):
                run_schedule(schedule, drive, session.clock, on_progress=on_progress)
            recorder.commit()
    log.info("characterization of %s recorded in %s", serial.label, recording)
    if on_step is not None:
        on_step("diagnosing")
    return diagnose_recording(recording, write_report=write_report, progress=on_step)
