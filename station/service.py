"""What the station's commands do: validate, run the procedure, record, answer QA.

This is the one place where a run meets the database. Everything the
operator got wrong (serial label, recipe, bench file, missing reason) is
refused here before the database or the bus is touched, so exit code 2 means
nothing was done. Once a run has started it is recorded whatever happens: a
failed unit as FAIL with its limits, a station problem as ERROR with its
reason, Ctrl-C as ABORTED; the recording of the bus goes beside the database.
"""

from __future__ import annotations

import logging
import tempfile
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import TYPE_CHECKING, cast

from drivers.base import CalibrationRecord
from station import __version__
from station.benches import BenchSession, BenchSpec, open_bench
from station.core import Trims
from station.errors import (
    DatabaseError,
    DatabaseRefused,
    DatabaseUnreachable,
    IdentityMismatch,
    InputError,
    StationError,
)
from station.limits import drift, drift_warnings
from station.paths import station_home
from station.procedure import (
    CalibrationRequest,
    calibrate_unit,
    check_identity,
    unit_on_bench,
)
from station.recipes import (
    DEFAULT_RECIPE,
    Recipe,
    RecipeError,
    available_recipes,
    load_recipe,
    parse_recipe,
)
from station.recording import metadata_path_for
from station.rows import VerificationRecord
from station.runs import RecipeRef, Run, RunKind, Verdict
from station.serials import Serial, parse_serial
from station.steps import Observer
from station.storage import (
    Backend,
    DbTarget,
    RunStore,
    backend_of,
    describe,
    open_store,
)
from station.store import Store

if TYPE_CHECKING:
    from station.pgstore import PostgresStore

log = logging.getLogger(__name__)

RECORDINGS_DIR = "recordings"
RECORDING_SUFFIX = ".blf"
"""Vector BLF: compressed, and read by every CAN tool a motion engineer owns."""


def recordings_dir(db_path: DbTarget) -> Path:
    """Recordings live beside the station's own database, one folder per unit; with a
    line's database they stay on the station's disk, in its home (records hold their
    SHA-256, the recordings stay where they were made)."""
    if backend_of(db_path) is Backend.POSTGRESQL:
        return station_home() / RECORDINGS_DIR
    return Path(db_path).parent / RECORDINGS_DIR


@dataclass(frozen=True)
class Station:
    """Where results go, which bench is attached, and who is at the station."""

    db_path: DbTarget  # a SQLite file, or a postgresql:// URL
    bench: BenchSpec
    operator: str


@dataclass(frozen=True)
class Calibration:
    """A finished run, and for field service the run whose trims the unit had."""

    run: Run
    previous: Run | None = None

    @property
    def drift(self) -> Trims | None:
        previous = self.previous.trims_after if self.previous is not None else None
        if previous is None or self.run.trims_after is None:
            return None
        return drift(previous, self.run.trims_after)


@contextmanager
def _store_for_runs(station: Station) -> Iterator[tuple[RunStore, str | None]]:
    """Where a run is recorded, and the warning it then carries (None: where it should be).

    A station's own file, or its line's database. A line's database that does not
    answer does not stop the line: the run goes into the station's spool, to be
    forwarded when it answers again; one that answers first gets what the spool holds,
    in order, so the line sees runs in the order they began.
    """
    target = station.db_path
    if backend_of(target) is not Backend.POSTGRESQL:
        with open_store(target) as store:
            yield store, None
        return
    from station import spool  # noqa: PLC0415 - psycopg only for a line's database

    path = spool.spool_path()
    try:
        line = open_store(target)
    except DatabaseUnreachable as exc:
        if not spool.reached(describe(target)):
            # Nothing answers at a URL this station never recorded into: a typo in the
            # host or port is not an outage, and no unit is calibrated into a spool for it.
            detail = " ".join(exc.detail.split())
            raise DatabaseRefused(exc.database, f"{detail}; this station has never "
                                  "reached it: check --db or STATION_DB (runs are spooled "
                                  "only for a line's database reached before)") from exc
        why = _one_line(exc)
        log.warning("%s: recording into this station's spool %s", why, path)
        with Store(path) as spooled:
            yield spooled, (f"recorded in this station's spool ({path}) because {why}; "
                            "`station sync` forwards it")
        return
    spool.note_reached(describe(target))
    with line:
        if path.exists():
            try:
                with Store(path) as spooled:
                    spool.forward(spooled, cast("PostgresStore", line))
            except DatabaseError as exc:  # the run goes on; the spool waits for the next one
                log.warning("the spool was not forwarded: %s", exc)
        yield line, None


def calibrate(station: Station, serial_label: str, recipe_name: str | None = None,
              observer: Observer | None = None) -> Calibration:
    """Production calibration of one unit (``station calibrate``)."""
    serial = parse_serial(serial_label)
    recipe = load_recipe(recipe_name or DEFAULT_RECIPE)
    with _store_for_runs(station) as (store, spooled):
        run = _new_run(station, serial, recipe, RunKind.CALIBRATE)
        if spooled is not None:
            run.warnings.append(spooled)
        return Calibration(_execute(store, station, serial, recipe, run, observer=observer,
                                    spooled=spooled is not None))


def recalibrate(station: Station, serial_label: str, reason: str, *,
                recipe_name: str | None = None, force: bool = False,
                observer: Observer | None = None) -> Calibration:
    """Field service: calibrate a unit that has a record, and show how far it drifted.

    Without ``--recipe`` the unit is recalibrated with the recipe it was last
    calibrated with (see ``_recipe_of``).
    """
    serial = parse_serial(serial_label)
    if not reason.strip():
        raise InputError("--reason must say why the unit is recalibrated")
    # A named recipe is checked before the database is even opened (nothing done on error).
    chosen = load_recipe(recipe_name) if recipe_name is not None else None
    with _store_for_runs(station) as (store, spooled):
        previous = store.last_stored(serial.label)
        if previous is None and not force:
            where = f"in the database {store.location}"
            if spooled is not None:
                where = (f"in this station's spool {store.location} (the line's database "
                         f"{describe(station.db_path)} did not answer)")
            runs = store.history(serial.label)
            if runs:
                # Its history lists runs: say why none of them counts as a calibration.
                last = runs[-1]
                verdict = last.verdict.value if last.verdict is not None else "still open"
                raise InputError(
                    f"{serial} has {len(runs)} run(s) {where} but none stored trims (the "
                    f"last, run {last.run_id}: {verdict}"
                    f"{f', {last.reason}' if last.reason else ''}); run `station calibrate "
                    f"{serial}`, or use --force to recalibrate it anyway")
            raise InputError(
                f"{serial} has no recorded calibration {where}; use --force to calibrate it "
                "anyway"
            )
        if chosen is not None:
            recipe = chosen
        elif previous is None:
            recipe = load_recipe(DEFAULT_RECIPE)
        else:
            recipe = _recipe_of(previous)
        run = _new_run(station, serial, recipe, RunKind.RECALIBRATE)
        if spooled is not None:
            run.warnings.append(spooled)
        run.service_reason = reason.strip()
        run.previous_run_id = previous.run_id if previous is not None else None
        previous_trims = previous.trims_after if previous is not None else None
        run = _execute(store, station, serial, recipe, run, observer=observer,
                       previous_trims=previous_trims, spooled=spooled is not None)
        return Calibration(run, previous)


def _recipe_of(previous: Run) -> Recipe:
    """The current version of the unit's last recipe; the very text it used if not shipped.

    A unit calibrated with a recipe file that is not (or no longer) among the
    shipped ones can still be recalibrated in the field exactly as before: the
    record carries the recipe text its run used.
    """
    name = previous.recipe.name
    if name in available_recipes():
        return load_recipe(name)
    text = previous.recipe.text
    if text is None:
        raise InputError(f"recipe {name!r} of run {previous.run_id} is neither shipped nor "
                         "kept in the database; name one with --recipe")
    try:
        return parse_recipe(text, source=f"{name} {previous.recipe.version} (database copy)")
    except RecipeError as exc:
        # Records outlive software: a text this version no longer reads is not run as a
        # guess. The history and statistics still read the run from its record alone.
        raise InputError(f"recipe {name!r} {previous.recipe.version} of run "
                         f"{previous.run_id} was written for another version of the station "
                         f"and does not read here ({'; '.join(exc.problems)}); "
                         "name one with --recipe") from None


def _new_run(station: Station, serial: Serial, recipe: Recipe, kind: RunKind) -> Run:
    return Run(
        serial=serial.label,
        kind=kind,
        recipe=RecipeRef(recipe.name, recipe.version, recipe.sha256),
        station_id=station.bench.station_id,
        operator=station.operator,
        software_version=__version__,
        bench=station.bench.name,
    )


def _execute(store: RunStore, station: Station, serial: Serial, recipe: Recipe, run: Run, *,
             observer: Observer | None, previous_trims: Trims | None = None,
             spooled: bool = False) -> Run:
    """Run the procedure and record the outcome, whatever it is."""
    if not station.bench.sees_drive_angle and not recipe.angle_free:
        # Refused before anything is recorded or sent: the operator picked a wrong pair.
        raise InputError(
            f"recipe {recipe.name} needs the drive's electrical angle, which a "
            f"{station.bench.transport.value} drive does not give (bench {station.bench.name}): "
            "use a recipe with a magnitude_sweep table or method = \"paper\""
        )
    folder = _recordings_folder(station.db_path, serial)
    with ExitStack() as stack:
        session: BenchSession | None = None
        failure: StationError | None = None
        try:
            session = stack.enter_context(unit_on_bench(station.bench, serial, observer))
        except IdentityMismatch:
            raise  # the operator's mistake: nothing recorded, nothing written to the drive
        except StationError as exc:
            failure = exc  # a bench that cannot be reached is recorded like any station error
        store.begin_run(run, recipe.text)
        try:
            try:
                if failure is not None:
                    raise failure
                assert session is not None
                recording = _recording_path(folder, serial, run, spooled=spooled)
                request = CalibrationRequest(serial, recipe, station.bench, recording)
                calibrate_unit(request, run, session, observer)
            finally:
                stack.close()  # the drive is disabled and the bench released before recording
        except KeyboardInterrupt as exc:
            run.verdict, run.reason = Verdict.ABORTED, str(exc) or "aborted by the operator"
        except StationError as exc:
            run.verdict, run.reason = Verdict.ERROR, str(exc)
        except OSError as exc:
            run.verdict, run.reason = Verdict.ERROR, f"{exc.filename}: {exc.strerror}"
        except Exception as exc:
            # A defect of the station, not of the unit: keep the traceback for the developers.
            log.exception("internal error during the run of %s", serial)
            run.verdict, run.reason = Verdict.ERROR, f"internal error: {exc!r}"
        finally:
            _finish(store, recipe, run, previous_trims)
    return run


def _recording_path(folder: Path, serial: Serial, run: Run, *, spooled: bool) -> Path:
    """Where the run's recording goes: named by its number in the database it is recorded
    in, which never names another recording there. A spool numbers its runs from 1 as
    the line does, in the same folder, so its recordings say so; a name already taken (a
    database replaced, its numbers begun again) gets the run's UUID as well, since a
    recording is never overwritten."""
    assert run.run_id is not None  # begun
    stem = f"{serial.label}-{'spool' if spooled else 'run'}{run.run_id:06d}"
    path = folder / f"{stem}{RECORDING_SUFFIX}"
    if path.exists() or metadata_path_for(path).exists():
        path = folder / f"{stem}-{run.run_uuid}{RECORDING_SUFFIX}"
    return path


def _recordings_folder(db_path: DbTarget, serial: Serial) -> Path:
    """The unit's recordings folder, made writable now: refused before any bus traffic."""
    folder = recordings_dir(db_path) / serial.label
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise InputError(f"recordings folder {folder}: cannot be written "
                         f"({exc.strerror}); the run's recording would be lost") from None
    return folder


def _finish(store: RunStore, recipe: Recipe, run: Run, previous_trims: Trims | None) -> None:
    """Whatever happened, the run gets a verdict and is recorded."""
    if run.verdict is None:
        run.verdict, run.reason = Verdict.ABORTED, "the station was stopped during the run"
    if previous_trims is not None and run.trims_after is not None:
        run.warnings.extend(drift_warnings(recipe.limits, previous_trims, run.trims_after))
    run.finished_at = datetime.now(UTC)
    try:
        store.finish_run(run)
    except DatabaseUnreachable as exc:
        _spool_finished(run, recipe, exc)
    # From here on the run is its record: what the caller shows is what was recorded.
    run.recipe = replace(run.recipe, text=recipe.text)
    run.freeze()


def _one_line(exc: DatabaseUnreachable) -> str:
    """The error as a warning says it: the database driver's message spans lines."""
    return " ".join(str(exc).split())


def _spool_finished(run: Run, recipe: Recipe, exc: DatabaseUnreachable) -> None:
    """A line that went away during the run: the finished run goes into the station's
    spool under its own UUID, and forwarding it finishes the open row the line keeps."""
    from station import spool  # noqa: PLC0415 - only a line's database gets here

    path = spool.spool_path()
    why = _one_line(exc)
    log.warning("%s when run %s finished: recording it into this station's spool %s",
                why, run.run_id, path)
    run.warnings.append(f"recorded in this station's spool ({path}) because {why} when "
                        "the run finished; `station sync` finishes it on the line")
    # The spool numbers its runs itself, and the line's numbers mean nothing there: the
    # line keeps the run's previous run on its open row.
    copy = replace(run, run_id=None, previous_run_id=None)
    with Store(path) as spooled:
        spooled.begin_run(copy, recipe.text)
        spooled.finish_run(copy)


# --- verify -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Verification:
    """The drive's stored trims against the last trims the station stored in it."""

    record: VerificationRecord
    calibration_record: CalibrationRecord
    recorded_verdict: Verdict | None

    @property
    def match(self) -> bool:
        return self.record.match


def verify(station: Station, serial_label: str) -> Verification:
    """Read the unit's trims and calibration record; compare with the database (read-only)."""
    serial = parse_serial(serial_label)
    with open_store(station.db_path) as store:
        recorded = store.last_stored(serial.label)
        with open_bench(station.bench, serial) as session:
            check_identity(session.drive, serial)
            drive_trims = session.drive.read_trims()
            calibration_record = session.drive.read_calibration_record()
        recorded_trims = recorded.trims_after if recorded is not None else None
        record = VerificationRecord(
            serial=serial.label,
            verified_at=datetime.now(UTC),
            station_id=station.bench.station_id,
            operator=station.operator,
            bench=station.bench.name,
            match=recorded_trims is not None and recorded_trims == drive_trims,
            drive_trims=drive_trims,
            recorded_run_id=recorded.run_id if recorded is not None else None,
            recorded_trims=recorded_trims,
        )
        store.add_verification(record)
    return Verification(record, calibration_record,
                        recorded.verdict if recorded is not None else None)
