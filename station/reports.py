"""Calibration reports for runs on record: which run, which recording, where the page goes.

``station report RUN_ID|SERIAL`` draws the page of any run a database holds;
``station calibrate`` draws its own run's page beside its recording as it
finishes; ``station analyze --report`` draws a recording alone. The page
itself is ``station.unit_report``; this module finds what it is drawn from
and says plainly when that is not there (a run that ended before motion has
no recording; a recording moved or changed since is named as such).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from station.errors import DatabaseError, InputError, StationError
from station.recording import sha256_of
from station.runs import Run
from station.serials import parse_serial
from station.storage import DbTarget, describe, open_store

if TYPE_CHECKING:
    from station.analysis.pipeline import Analysis

log = logging.getLogger(__name__)

REPORT_SUFFIX = ".calibration.html"

def report_path_for(recording: Path) -> Path:
    """Beside ``SN123-run000001.blf``: ``SN123-run000001.calibration.html``."""
    return recording.with_name(recording.stem + REPORT_SUFFIX)


@dataclass(frozen=True)
class UnitReport:
    """A page written, the run and recording it shows, and what it could not show."""

    path: Path
    serial: str
    run: Run | None
    recording: str | None
    notes: tuple[str, ...] = ()

    def as_dict(self) -> dict[str, Any]:
        return {"report": str(self.path), "serial": self.serial,
                "run_id": self.run.run_id if self.run is not None else None,
                "recording": self.recording, "notes": list(self.notes)}


def _chosen_run(runs: list[Run], serial: str, where: str) -> Run:
    """A serial's page is that of its newest calibration with a recording (what a
    technician asking "how was this unit calibrated" means), else its newest run."""
    if not runs:
        raise InputError(f"no runs of {serial} are recorded in {where}")
    with_recording = [r for r in runs if r.recording]
    return (with_recording or runs)[-1]


def find_run(db_path: DbTarget, key: str) -> tuple[Run, list[Run]]:
    """The run ``key`` names (a run ID, or a serial for its newest calibration) and its
    unit's history, oldest first."""
    with open_store(db_path) as store:
        if key.strip().isdigit():
            run = store.get_run(int(key))
            return run, store.history(run.serial)
        serial = parse_serial(key).label
        runs = store.history(serial)
        return _chosen_run(runs, serial, describe(db_path)), runs


def _settle_periods(run: Run) -> int | None:
    """How long the run's recipe let each hold settle: holds as short as a Modbus bench's
    are too short to judge their own settling, and the run itself did not judge them."""
    if run.recipe.text is None:
        return None
    from station.recipes import RecipeError, parse_recipe  # noqa: PLC0415

    try:
        return parse_recipe(run.recipe.text).motion.settle_periods
    except RecipeError:  # a recipe this version no longer reads: judged from the data
        return None


def _analysed(recording: Path, settle_periods: int | None = None
              ) -> tuple[Analysis | None, str | None]:
    """The recording analysed as ``station analyze`` does (with the run's own settling
    where known), or why it could not be."""
    from station.analysis.pipeline import AnalysisOptions, analyze  # noqa: PLC0415 - scipy
    from station.analysis.reader import read_recording  # noqa: PLC0415 - python-can

    settle = None if settle_periods is None else float(settle_periods)
    try:
        return analyze(read_recording(recording), AnalysisOptions(settle_periods=settle),
                       estimate_required=False), None
    except InputError as exc:  # too short, unreadable: the page shows the record alone
        return None, f"the recording could not be analysed: {exc}"
    except (ValueError, ArithmeticError) as exc:
        # A recording the analysis cannot take is a defect to fix there, but the page of a
        # run judged already must still be drawn: it says so instead.
        log.warning("analysing %s failed", recording, exc_info=True)
        return None, f"the recording could not be analysed: {type(exc).__name__}: {exc}"


def write_run_report(run: Run, history: list[Run], out: Path | None = None) -> UnitReport:
    """The page of a run on record, beside its recording unless ``out`` says where."""
    recording = Path(run.recording) if run.recording else None
    if recording is None and out is None:
        raise InputError(f"run {run.run_id} of {run.serial} has no recording to put a "
                         "report beside: give --out")
    notes: list[str] = []
    analysis: Analysis | None = None
    if recording is None:
        notes.append(f"run {run.run_id} has no recording: it ended before the motor moved"
                     + (f" ({run.reason})" if run.reason else ""))
    elif not recording.exists():
        notes.append(f"the recording {recording} is no longer there: the page shows the "
                     "record alone")
    else:
        if run.recording_sha256 and sha256_of(recording) != run.recording_sha256:
            notes.append(f"the recording {recording} is not the file run {run.run_id} "
                         "recorded (its sha256 differs): the figures may not be this run's")
        analysis, problem = _analysed(recording, _settle_periods(run))
        if problem is not None:
            notes.append(problem)
    if out is None:
        assert recording is not None  # refused above
        out = report_path_for(recording)
    from station.unit_report import write_unit_report  # noqa: PLC0415 - matplotlib, scipy

    write_unit_report(out, source=str(recording) if recording else "none", analysis=analysis,
                      run=run, history=history, notes=notes)
    return UnitReport(out, run.serial, run, str(recording) if recording else None, tuple(notes))


def report(db_path: DbTarget, key: str, out: Path | None = None) -> UnitReport:
    """``station report``: the page of one run, by ID or by its unit's serial."""
    run, history = find_run(db_path, key)
    return write_run_report(run, history, out)


def report_finished(db_path: DbTarget, run: Run) -> UnitReport | None:
    """The page a calibration leaves beside its recording as it finishes.

    Never changes the run's outcome: the unit is judged and recorded already, so a
    page that cannot be drawn is a warning, not an error of the run.
    """
    if not run.recording:
        return None
    try:
        try:
            with open_store(db_path) as store:
                history = store.history(run.serial)
        except DatabaseError as exc:  # spooled: the line's history is out of reach
            log.warning("the report shows no history: %s", exc)
            history = [run]
        return write_run_report(run, history)
    except (StationError, OSError) as exc:
        log.warning("no report was written for run %s: %s", run.run_id, exc)
        return None


def report_recording(recording: Path, analysis: Analysis, out: Path | None = None
                     ) -> UnitReport:
    """``station analyze --report``: the recording alone, no record."""
    from station.unit_report import write_unit_report  # noqa: PLC0415 - matplotlib, scipy

    target = out if out is not None else report_path_for(recording)
    write_unit_report(target, source=str(recording), analysis=analysis)
    return UnitReport(target, analysis.timeline.metadata.serial, None, str(recording))
