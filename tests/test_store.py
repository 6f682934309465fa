"""The results database keeps every run whole, migrates safely, and answers QA.

Runs are the station's traceability: a field lost on the way to SQLite, a
migration half-applied, or a file held open after the station is done with it
would each surface months later on the line, so they are tested here.
"""

from __future__ import annotations

import copy as copy_module
import dataclasses
import hashlib
import math
import os
import pickle
import re
import sqlite3
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, fields, replace
from datetime import UTC, datetime, timedelta, timezone
from importlib.resources import files
from pathlib import Path

import pytest

from station.core import Trims
from station.errors import DatabaseError, DatabasePathError, ExitCode, InputError
from station.migrations import MIGRATIONS_PACKAGE, load_migrations
from station.owners import ProcessInfo, RunOwner, current_owner, probe_process, why_gone
from station.rows import RunFilter, VerificationRecord
from station.runs import (
    FrozenRecord,
    LimitCheck,
    LimitName,
    RecipeRef,
    Ripple,
    Run,
    RunKind,
    Verdict,
    utc_iso,
)
from station.storage import RunStore
from station.store import Store

T0 = datetime(2025, 3, 1, 8, 0, 0, 123456, tzinfo=UTC)


def _recipe(name: str = "default", version: str = "1.0") -> tuple[RecipeRef, str]:
    text = f'name = "{name}"\nversion = "{version}"\n'
    return RecipeRef(name, version, hashlib.sha256(text.encode()).hexdigest()), text


def _run(
    serial: str = "SN1",
    *,
    started_at: datetime = T0,
    station_id: int = 1,
    recipe: str = "default",
    kind: RunKind = RunKind.CALIBRATE,
) -> Run:
    ref, _ = _recipe(recipe)
    return Run(
        serial=serial,
        kind=kind,
        recipe=ref,
        station_id=station_id,
        operator="alice",
        software_version="0.1.0",
        bench="sim",
        started_at=started_at,
    )


def _begin(store: RunStore, run: Run) -> Run:
    _, text = _recipe(run.recipe.name, run.recipe.version)
    store.begin_run(run, text)
    return run


def _record(store: RunStore, run: Run, verdict: Verdict = Verdict.PASS, *,
            stored: bool = True) -> Run:
    """Begin and finish ``run`` as the procedure would, with every result filled in."""
    _begin(store, run)
    run.verdict = verdict
    run.finished_at = run.started_at + timedelta(seconds=93.5)
    run.trims_stored = stored
    store.finish_run(run)
    return run


def _finish(store: RunStore, run: Run, verdict: Verdict = Verdict.PASS) -> Run:
    """Finish an open run with whatever it learnt so far; a finish needs a verdict and time."""
    run.verdict = verdict
    run.finished_at = run.started_at + timedelta(seconds=42)
    store.finish_run(run)
    return run


def _full_run(previous_run_id: int) -> Run:
    """A field-service run with every field set, none at its default."""
    run = _run(kind=RunKind.RECALIBRATE)
    run.service_reason = "noisy at 300 rpm"
    run.previous_run_id = previous_run_id
    run.finished_at = T0 + timedelta(minutes=2, microseconds=7)
    run.verdict = Verdict.FAIL
    run.reason = "offset_sigma_mA above limit"
    run.limits = (
        LimitCheck(LimitName.OFFSET_A, 12.5, -300.0, 300.0, "mA", True),
        LimitCheck(LimitName.OFFSET_SIGMA, 4.25, None, 2.0, "mA", False, "sigma 4.25 > 2"),
        LimitCheck(LimitName.H1_REDUCTION, None, 6.0, None, "dB", None, "no after measurement"),
    )
    run.trims_before = Trims(1.0, -2.0, 10001.0, 9999.0)
    run.trims_after = Trims(13.0, -7.0, 10020.0, 9980.0)
    run.trims_stored = True
    run.trims_estimated = Trims(12.625, -7.25, 10019.875, 9980.125)
    run.uncertainty = Trims(4.25, 3.5, 1.25, 1.5)
    run.before = Ripple(0.0123, 0.0045)
    run.after = Ripple(0.0011, 0.0007)
    run.method = "coherent"
    run.fit = {"h1": {"r2": 0.998, "chi2_reduced": 1.7}, "points": [1, 2, 3]}
    run.warnings = ["gain split swept at zero offsets", "1 sample lost"]
    run.recording = "/var/station/recordings/SN1-0002.blf"
    run.recording_sha256 = "ab" * 32
    run.motion_s = 187.25
    return run


def _write_migrations(folder: Path, scripts: dict[str, str]) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    for name, sql in scripts.items():
        (folder / name).write_text(sql)
    return folder


def _raw(path: Path) -> sqlite3.Connection:
    """A connection behind the store's back, to see what is really in the file."""
    return sqlite3.connect(path)


def _user_version(path: Path) -> int:
    conn = _raw(path)
    try:
        return int(conn.execute("PRAGMA user_version").fetchone()[0])
    finally:
        conn.close()


def _tables(path: Path) -> set[str]:
    conn = _raw(path)
    try:
        return {row[0] for row in conn.execute("SELECT name FROM sqlite_master WHERE type='table'")}
    finally:
        conn.close()


@pytest.fixture
def db_path(tmp_path: Path) -> Path:
    return tmp_path / "nested" / "dir" / "station.db"


@pytest.fixture
def store(db_path: Path) -> Iterator[Store]:
    """An open store; tests close it with ``with``, this only catches a failed test's."""
    opened = Store(db_path)
    yield opened
    opened.close()


# -- migrations -------------------------------------------------------------------


def test_fresh_file_gets_every_shipped_migration_and_the_newest_version(db_path: Path) -> None:
    newest = load_migrations(files(MIGRATIONS_PACKAGE))[-1].number
    with Store(db_path) as store:
        assert store.schema_version == newest
    assert _user_version(db_path) == newest
    assert {"runs", "recipes", "limit_checks", "verifications"} <= _tables(db_path)


def test_reopening_applies_no_migration_twice(tmp_path: Path) -> None:
    migrations = _write_migrations(
        tmp_path / "migrations",
        {
            "0001_counter.sql": "CREATE TABLE applied (n INTEGER);",
            "0002_count.sql": "INSERT INTO applied VALUES (2);",
        },
    )
    path = tmp_path / "station.db"
    for _ in range(3):
        Store(path, migrations=migrations).close()
    conn = _raw(path)
    try:
        assert conn.execute("SELECT n FROM applied").fetchall() == [(2,)]
    finally:
        conn.close()
    assert _user_version(path) == 2


def test_failed_migration_leaves_the_database_as_it_was(tmp_path: Path) -> None:
    migrations = _write_migrations(
        tmp_path / "migrations",
        {
            "0001_first.sql": "CREATE TABLE first (n INTEGER);",
            "0002_broken.sql": (
                "CREATE TABLE second (n INTEGER);\nINSERT INTO no_such_table VALUES (1);"
            ),
        },
    )
    path = tmp_path / "station.db"
    with pytest.raises(DatabaseError, match=r"0002_broken\.sql.*rolled back") as error:
        Store(path, migrations=migrations)
    assert str(path) in str(error.value)
    assert _user_version(path) == 1
    assert "first" in _tables(path)
    assert "second" not in _tables(path)

    # Once fixed, the same file migrates on.
    (migrations / "0002_broken.sql").write_text("CREATE TABLE second (n INTEGER);")
    with Store(path, migrations=migrations) as store:
        assert store.schema_version == 2


def test_database_from_newer_software_is_refused(db_path: Path) -> None:
    Store(db_path).close()
    newer = _user_version(db_path) + 1
    conn = _raw(db_path)
    try:
        conn.execute(f"PRAGMA user_version = {newer}")
    finally:
        conn.close()
    with pytest.raises(DatabaseError, match=f"schema version {newer} is newer") as error:
        Store(db_path)
    assert str(db_path) in str(error.value)
    assert error.value.exit_code is ExitCode.STATION


@pytest.mark.parametrize(
    "names",
    [
        ["0001_a.sql", "0003_c.sql"],  # a gap
        ["0002_b.sql"],  # not starting at 1
        ["0001_a.sql", "0001_b.sql"],  # a number twice
        ["1_a.sql"],  # misnamed: would be skipped silently otherwise
    ],
)
def test_misnumbered_or_misnamed_migrations_are_refused(tmp_path: Path, names: list[str]) -> None:
    migrations = _write_migrations(tmp_path / "m", dict.fromkeys(names, "SELECT 1;"))
    with pytest.raises(DatabaseError, match="migration"):
        Store(tmp_path / "station.db", migrations=migrations)
    assert not (tmp_path / "station.db").exists()


def test_stations_opening_a_new_file_together_all_succeed(tmp_path: Path) -> None:
    path = tmp_path / "shared.db"
    start = threading.Barrier(4)
    errors: list[BaseException] = []

    def open_store() -> None:
        start.wait()
        try:
            Store(path).close()
        except BaseException as exc:  # reported below, on the test's thread
            errors.append(exc)

    threads = [threading.Thread(target=open_store) for _ in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert _user_version(path) == load_migrations(files(MIGRATIONS_PACKAGE))[-1].number


def test_file_that_is_not_a_database_is_a_database_error_naming_it(tmp_path: Path) -> None:
    path = tmp_path / "station.db"
    path.write_bytes(b"this is not sqlite" * 100)
    with pytest.raises(DatabaseError, match="not a database") as error:
        Store(path)
    assert str(path) in str(error.value)


# -- lifetime ---------------------------------------------------------------------


def test_store_is_closed_after_with_and_refuses_use(db_path: Path) -> None:
    with Store(db_path) as store:
        _record(store, _run())
        open_inside = not store.closed
    assert open_inside
    assert store.closed
    # SQLite removes the WAL file only when the last connection to the file closes.
    assert not db_path.with_name(db_path.name + "-wal").exists()
    with pytest.raises(DatabaseError, match="closed"):
        store.history("SN1")
    store.close()  # a second close is harmless


def test_store_is_closed_when_the_with_body_raises(db_path: Path) -> None:
    with pytest.raises(RuntimeError), Store(db_path) as store:
        raise RuntimeError("operator pressed stop")
    assert store.closed


# -- runs -------------------------------------------------------------------------


def test_finished_run_reads_back_with_every_field(store: Store) -> None:
    with store:
        first = _record(store, _run())
        assert first.run_id is not None
        run = _full_run(previous_run_id=first.run_id)
        unset = [f.name for f in fields(Run) if getattr(run, f.name) in (None, (), [], False)]
        assert unset == ["run_id"], "the round trip must cover every field"
        _, text = _recipe()
        run_id = store.begin_run(run, text)
        assert run.run_id == run_id
        store.finish_run(run)
        assert store.get_run(run_id) == run


def test_begun_run_is_kept_open_until_finished_even_across_a_crash(db_path: Path) -> None:
    with Store(db_path) as store:
        run = _begin(store, _run())
    # A new process after the crash: the run is there, without a verdict.
    with Store(db_path) as store:
        (found,) = store.history(run.serial)
        assert found == run
        assert found.verdict is None
        run.verdict = Verdict.ERROR
        run.reason = "station restarted during the run"
        run.finished_at = T0 + timedelta(hours=1)
        store.finish_run(run)
        assert store.history(run.serial)[0].verdict is Verdict.ERROR


def test_every_verdict_and_kind_fits_the_schema(store: Store) -> None:
    with store:
        for kind in RunKind:
            for verdict in Verdict:
                run = _record(store, _run(kind=kind), verdict)
                assert run.run_id is not None
                back = store.get_run(run.run_id)
                assert (back.kind, back.verdict) == (kind, verdict)


def test_begin_refuses_recipe_text_that_does_not_match_its_hash(store: Store) -> None:
    with store:
        with pytest.raises(ValueError, match="sha256"):
            store.begin_run(_run(), "edited after hashing")
        assert store.query(RunFilter()) == []


def test_run_cannot_point_at_a_previous_run_that_does_not_exist(store: Store) -> None:
    run = _run(kind=RunKind.RECALIBRATE)
    run.previous_run_id = 4242
    with store, pytest.raises(DatabaseError, match="FOREIGN KEY"):
        _begin(store, run)


def test_unknown_run_is_an_input_error(store: Store) -> None:
    with store:
        with pytest.raises(InputError, match="no run 99"):
            store.get_run(99)
        ghost = _run()
        ghost.run_id = 99
        ghost.verdict, ghost.finished_at = Verdict.PASS, T0
        with pytest.raises(InputError, match="no run 99"):
            store.finish_run(ghost)


def test_nan_estimate_comes_back_as_nan_not_as_missing_trims(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        run.trims_estimated = Trims(math.nan, 1.0, 10000.0, 10000.0)
        _finish(store, run)
        assert run.run_id is not None
        back = store.get_run(run.run_id).trims_estimated
        assert back is not None
        assert math.isnan(back.offset_a_mA)
        assert (back.offset_b_mA, back.gain_a, back.gain_b) == (1.0, 10000.0, 10000.0)


def test_recipe_text_is_kept_once_per_hash(store: Store) -> None:
    with store:
        a = _record(store, _run())
        _record(store, _run())
        other = _record(store, _run(recipe="paper"))
        assert store.recipe_text(a.recipe.sha256) == _recipe()[1]
        assert store.recipe_text(other.recipe.sha256) == _recipe("paper")[1]
        assert store.recipe_text("0" * 64) is None


# -- limit checks -----------------------------------------------------------------


def test_limit_checks_round_trip_in_order_including_not_applied(store: Store) -> None:
    checks = (
        LimitCheck(LimitName.H2_AFTER, 0.002, None, 0.01, "m/s²", True),
        LimitCheck(LimitName.ESTIMATE, None, None, None, "", None, "not enough points"),
        LimitCheck(LimitName.GAIN_A, 10400.0, 9000.0, 10300.0, "1/10000", False, "too high"),
    )
    with store:
        run = _begin(store, _run())
        run.limits = checks
        _finish(store, run)
        assert run.run_id is not None
        back = store.get_run(run.run_id)
        assert back.limits == checks
        assert back.failed_limits == (checks[2],)


@pytest.mark.parametrize(
    ("second_limits", "refusal"),
    [
        ((), "a finished run (verdict set) cannot be changed"),
        ((LimitCheck(LimitName.OFFSET_B, 9.0, -5.0, 5.0, "mA", False),),
         "a finished run cannot be given more limit checks"),
        # The same limit again: refused as a change to a finished run, not as a duplicate key.
        ((LimitCheck(LimitName.OFFSET_A, 9.0, -5.0, 5.0, "mA", False),),
         "a finished run cannot be given more limit checks"),
    ],
    ids=["verdict-only", "another-limit", "same-limit"],
)
def test_an_open_run_is_finished_once_and_then_never_again(
    store: Store, db_path: Path, second_limits: tuple[LimitCheck, ...], refusal: str
) -> None:
    with store:
        run = _begin(store, _run())
        run.limits = (LimitCheck(LimitName.OFFSET_A, 1.0, -5.0, 5.0, "mA", True),)
        _finish(store, run, Verdict.PASS)
        first = replace(run, limits=run.limits, warnings=list(run.warnings))
        run.verdict, run.reason, run.limits = Verdict.FAIL, "second thoughts", second_limits
        with pytest.raises(DatabaseError, match=re.escape(refusal)) as error:
            store.finish_run(run)
        assert str(db_path) in str(error.value)
        assert run.run_id is not None
        assert store.get_run(run.run_id) == first


def test_finishing_needs_a_verdict_and_a_time(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        with pytest.raises(ValueError, match="verdict and finishing time"):
            store.finish_run(run)
        run.verdict = Verdict.PASS
        with pytest.raises(ValueError, match="verdict and finishing time"):
            store.finish_run(run)
        assert run.run_id is not None
        assert store.get_run(run.run_id).verdict is None


def test_a_limit_checked_twice_is_refused_and_nothing_changes(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        check = LimitCheck(LimitName.OFFSET_A, 1.0, -5.0, 5.0, "mA", True)
        run.limits = (check, check)
        run.verdict, run.finished_at = Verdict.PASS, T0
        with pytest.raises(ValueError, match="twice"):
            store.finish_run(run)
        assert run.run_id is not None
        assert store.get_run(run.run_id).verdict is None  # the failed finish changed nothing


def test_limits_of_many_runs_each_go_to_their_own_run(store: Store) -> None:
    with store:
        for i in range(30):
            run = _begin(store, _run(f"SN{i % 3}"))
            run.limits = (LimitCheck(LimitName.OFFSET_A, float(i), -50.0, 50.0, "mA", True),)
            _finish(store, run)
        for run in store.query(RunFilter()):
            assert run.run_id is not None
            assert [check.value for check in run.limits] == [float(run.run_id - 1)]


# -- history and queries ----------------------------------------------------------


def test_history_is_oldest_first_and_only_of_that_unit(store: Store) -> None:
    with store:
        ids: dict[str, list[int | None]] = {"SN1": [], "SN2": []}
        for i in range(6):
            serial = "SN1" if i % 3 else "SN2"
            ids[serial].append(_record(store, _run(serial)).run_id)
        assert [run.run_id for run in store.history("SN1")] == ids["SN1"]
        assert [run.run_id for run in store.history("SN2")] == ids["SN2"]
        assert store.history("SN3") == []


def test_last_stored_is_the_latest_run_that_stored_trims(store: Store) -> None:
    with store:
        assert store.last_stored("SN1") is None
        stored = _record(store, _run())
        _record(store, _run(), Verdict.FAIL, stored=False)
        _record(store, _run("SN2"))
        _record(store, _run(), Verdict.ERROR, stored=False)
        assert store.last_stored("SN1") == stored


def _populate(store: Store) -> list[Run]:
    """Runs spread over serials, days, recipes, verdicts and stations."""
    runs = []
    verdicts = list(Verdict)
    for i in range(24):
        run = _run(
            f"SN{i % 4}",
            started_at=T0 + timedelta(days=i),
            station_id=1 + i % 3,
            recipe="paper" if i % 5 == 0 else "default",
        )
        runs.append(_record(store, run, verdicts[i % len(verdicts)]))
    return runs


_FILTERS: dict[str, tuple[RunFilter, Callable[[Run], bool]]] = {
    "none": (RunFilter(), lambda run: True),
    "serial": (RunFilter(serial="SN2"), lambda run: run.serial == "SN2"),
    # Bounds are inclusive, to the microsecond.
    "since": (
        RunFilter(since=T0 + timedelta(days=20)),
        lambda run: run.started_at >= T0 + timedelta(days=20),
    ),
    "until": (
        RunFilter(until=T0 + timedelta(days=3)),
        lambda run: run.started_at <= T0 + timedelta(days=3),
    ),
    "since_until": (
        RunFilter(since=T0 + timedelta(days=5), until=T0 + timedelta(days=7)),
        lambda run: T0 + timedelta(days=5) <= run.started_at <= T0 + timedelta(days=7),
    ),
    "recipe": (RunFilter(recipe="paper"), lambda run: run.recipe.name == "paper"),
    "verdict": (RunFilter(verdict=Verdict.FAIL), lambda run: run.verdict is Verdict.FAIL),
    "station": (RunFilter(station_id=2), lambda run: run.station_id == 2),
    "combined": (
        RunFilter(serial="SN1", station_id=2, verdict=Verdict.FAIL),
        lambda run: (run.serial, run.station_id, run.verdict) == ("SN1", 2, Verdict.FAIL),
    ),
}


@pytest.mark.parametrize("name", list(_FILTERS))
def test_query_filter_selects_exactly_the_matching_runs(store: Store, name: str) -> None:
    run_filter, wanted = _FILTERS[name]
    with store:
        runs = _populate(store)
        expected = [run.run_id for run in runs if wanted(run)]
        assert expected, "the population must exercise the filter"
        assert [run.run_id for run in store.query(run_filter)] == expected


def test_query_bounds_in_another_timezone_mean_the_same_moment(store: Store) -> None:
    with store:
        runs = _populate(store)
        since = (T0 + timedelta(days=22)).astimezone(timezone(timedelta(hours=-5)))
        assert [run.run_id for run in store.query(RunFilter(since=since))] == [
            run.run_id for run in runs[22:]
        ]


def test_query_limit_keeps_the_newest_runs_oldest_first(store: Store) -> None:
    with store:
        runs = _populate(store)
        sn1 = [run.run_id for run in runs if run.serial == "SN1"]
        assert [run.run_id for run in store.query(RunFilter(serial="SN1", limit=3))] == sn1[-3:]
        assert [run.run_id for run in store.query(RunFilter(limit=100))] == [
            run.run_id for run in runs
        ]
        assert store.query(RunFilter(limit=0)) == []


def test_negative_limit_is_refused() -> None:
    with pytest.raises(ValueError, match="limit"):
        RunFilter(limit=-1)


# -- verifications ----------------------------------------------------------------


def test_verifications_round_trip_per_unit_oldest_first(store: Store) -> None:
    with store:
        stored = _record(store, _run())
        found = VerificationRecord(
            serial="SN1",
            verified_at=T0 + timedelta(days=200),
            station_id=2,
            operator="bob",
            bench="line-2",
            match=False,
            drive_trims=Trims(0.0, 0.0, 10000.0, 10000.0),
            recorded_run_id=stored.run_id,
            recorded_trims=Trims(13.0, -7.0, 10020.0, 9980.0),
        )
        unknown = replace(
            found,
            verified_at=found.verified_at + timedelta(hours=1),
            match=True,
            recorded_run_id=None,
            recorded_trims=None,
        )
        other = replace(found, serial="SN2", recorded_run_id=None, recorded_trims=None)
        first_id = store.add_verification(found)
        assert store.add_verification(unknown) > first_id
        store.add_verification(other)
        assert store.verifications("SN1") == [found, unknown]
        assert store.verifications("SN2") == [other]
        assert store.verifications("SN3") == []


# -- append-only ------------------------------------------------------------------


@dataclass(frozen=True)
class _Tamperable:
    """A database holding one of everything a tamperer could reach for."""

    finished: int
    open: int
    sha256: str


def _tamperable(db_path: Path) -> _Tamperable:
    with Store(db_path) as store:
        finished = _begin(store, _run())
        finished.limits = (LimitCheck(LimitName.OFFSET_A, 1.0, -5.0, 5.0, "mA", False),)
        _finish(store, finished, Verdict.FAIL)
        opened = _begin(store, _run("SN2"))
        store.add_verification(VerificationRecord(
            serial="SN1", verified_at=T0, station_id=1, operator="bob", bench="sim",
            match=True, drive_trims=Trims(), recorded_run_id=finished.run_id,
            recorded_trims=Trims(),
        ))
    assert finished.run_id is not None and opened.run_id is not None
    return _Tamperable(finished.run_id, opened.run_id, finished.recipe.sha256)


def _snapshot(path: Path) -> dict[str, list[tuple[object, ...]]]:
    conn = _raw(path)
    try:
        return {
            table: conn.execute(f"SELECT * FROM {table} ORDER BY 1, 2").fetchall()
            for table in ("runs", "limit_checks", "verifications", "recipes")
        }
    finally:
        conn.close()


_TAMPERING = {
    "change a finished run's verdict": (
        "UPDATE runs SET verdict = 'pass' WHERE run_id = :finished",
        "a finished run (verdict set) cannot be changed"),
    "change every finished run's reason": (
        "UPDATE runs SET reason = 'edited' WHERE verdict IS NOT NULL",
        "a finished run (verdict set) cannot be changed"),
    "reopen a finished run": (
        "UPDATE runs SET verdict = NULL WHERE run_id = :finished",
        "a finished run (verdict set) cannot be changed"),
    "rename an open run's unit": (
        "UPDATE runs SET serial = 'SN9' WHERE run_id = :open",
        "what a run recorded when it began cannot be changed"),
    "rewrite an open run's owner": (
        "UPDATE runs SET owner = NULL WHERE run_id = :open",
        "what a run recorded when it began cannot be changed"),
    "delete a finished run": ("DELETE FROM runs WHERE run_id = :finished",
                              "a run cannot be deleted"),
    "delete an open run": ("DELETE FROM runs WHERE run_id = :open", "a run cannot be deleted"),
    "replace a finished run": (
        "INSERT OR REPLACE INTO runs SELECT * FROM runs WHERE run_id = :finished",
        "a run cannot be replaced"),
    "pass a failed limit": ("UPDATE limit_checks SET passed = 1",
                            "a limit check cannot be changed"),
    "delete a limit check": ("DELETE FROM limit_checks", "a limit check cannot be deleted"),
    "replace a limit check": (
        "INSERT OR REPLACE INTO limit_checks SELECT * FROM limit_checks",
        "limit checks are append-only"),  # of a finished run: two triggers refuse it
    "add a limit check to a finished run": (
        "INSERT INTO limit_checks (run_id, name, position, unit) "
        "VALUES (:finished, 'gain_a', 5, '')",
        "a finished run cannot be given more limit checks"),
    "change a verification": ("UPDATE verifications SET trims_match = 0",
                              "a verification cannot be changed"),
    "delete a verification": ("DELETE FROM verifications", "a verification cannot be deleted"),
    "replace a verification": (
        "INSERT OR REPLACE INTO verifications SELECT * FROM verifications",
        "a verification cannot be replaced"),
    "change a recipe text": ("UPDATE recipes SET text = 'max_h1 = 1e9' WHERE sha256 = :sha256",
                             "a stored recipe text cannot be changed"),
    "delete a recipe": ("DELETE FROM recipes", "a stored recipe text cannot be deleted"),
}


@pytest.mark.parametrize("what", list(_TAMPERING))
def test_a_raw_connection_cannot_change_or_remove_what_was_recorded(
    db_path: Path, what: str
) -> None:
    sql, refusal = _TAMPERING[what]
    ids = _tamperable(db_path)
    before = _snapshot(db_path)
    conn = _raw(db_path)  # a technician's sqlite3 shell: no station code involved
    try:
        with pytest.raises(sqlite3.IntegrityError, match=re.escape(refusal)):
            conn.execute(sql, {"finished": ids.finished, "open": ids.open,
                               "sha256": ids.sha256})
        conn.commit()
    finally:
        conn.close()
    assert _snapshot(db_path) == before


def test_replacing_a_stored_recipe_is_a_no_op_not_a_rewrite(db_path: Path) -> None:
    ids = _tamperable(db_path)
    before = _snapshot(db_path)
    conn = _raw(db_path)
    try:
        conn.execute("INSERT OR REPLACE INTO recipes VALUES (?, 'x', '9', 'tampered', 'now')",
                     (ids.sha256,))
        conn.commit()
    finally:
        conn.close()
    assert _snapshot(db_path) == before


def test_a_raw_connection_may_finish_an_open_run_once(db_path: Path) -> None:
    ids = _tamperable(db_path)
    conn = _raw(db_path)
    try:
        conn.execute("UPDATE runs SET verdict = 'error', finished_at = ? WHERE run_id = ?",
                     (utc_iso(T0), ids.open))
        conn.commit()
        with pytest.raises(sqlite3.IntegrityError, match="cannot be changed"):
            conn.execute("UPDATE runs SET verdict = 'pass' WHERE run_id = ?", (ids.open,))
    finally:
        conn.close()
    with Store(db_path) as store:
        assert store.get_run(ids.open).verdict is Verdict.ERROR


# -- interrupted runs -------------------------------------------------------------

HOST = "line3-a"
BOOT = "6f1c0f7e-0000-4000-8000-000000000001"
NS = "pid:[4026531836]"
DEAD_PID, LIVE_PID, REUSED_PID, ZOMBIE_PID, STATION_PID = 1111, 2222, 3333, 4444, 9999


def _owner(pid: int, *, host: str = HOST, boot: str | None = BOOT, start: int | None = 500,
           ns: str | None = NS) -> RunOwner:
    return RunOwner(host=host, pid=pid, boot_id=boot, start_time=start, pid_ns=ns)


HERE = _owner(STATION_PID, start=900)


def _process_table(pid: int) -> ProcessInfo | None:
    """This machine, as the tests play it: which of the owners' pids still run."""
    return {
        LIVE_PID: ProcessInfo(start_time=500),
        REUSED_PID: ProcessInfo(start_time=777),  # the pid now names a later process
        ZOMBIE_PID: ProcessInfo(start_time=500, ended=True),
        STATION_PID: ProcessInfo(start_time=900),
    }.get(pid)


@pytest.mark.parametrize(
    ("owner", "why"),
    [
        (_owner(DEAD_PID), "the process no longer exists"),
        (_owner(REUSED_PID), "its pid now belongs to another process"),
        (_owner(ZOMBIE_PID), "the process has exited"),
        (_owner(LIVE_PID, boot="an-earlier-boot"), "the machine has restarted since"),
        # Rebooted: even a pid that happens to run again proves nothing about the old one.
        (_owner(DEAD_PID, boot="an-earlier-boot", ns="pid:[1]"), "the machine has restarted"),
        (_owner(LIVE_PID), None),
        (_owner(LIVE_PID, start=None), None),  # its start time was never known: no proof
        (_owner(STATION_PID, start=900), None),  # this very process
        (_owner(DEAD_PID, host="line3-b"), None),  # another machine's processes are unseen
        (_owner(DEAD_PID, host="line3-b", boot="an-earlier-boot"), None),
        (_owner(DEAD_PID, boot=None), None),  # no boot id: a reboot cannot be ruled out
        (_owner(DEAD_PID, ns="pid:[4026532000]"), None),  # another container's pids
        (_owner(DEAD_PID, ns=None), None),
    ],
    ids=["dead", "pid-reused", "zombie", "rebooted", "rebooted-other-ns", "alive",
         "alive-start-unknown", "this-process", "other-host", "other-host-other-boot",
         "no-boot-id", "other-pid-namespace", "unknown-pid-namespace"],
)
def test_an_owner_is_gone_only_when_provably_so(owner: RunOwner, why: str | None) -> None:
    found = why_gone(owner, HERE, _process_table)
    if why is None:
        assert found is None
    else:
        assert found is not None and found.startswith(why)


def test_this_machine_sees_a_live_process_a_dead_one_and_a_zombie() -> None:
    me = current_owner()
    assert me.pid == os.getpid() and me.host
    if me.boot_id is None or me.start_time is None:
        pytest.skip("not Linux: no boot id or process start time to judge by")
    assert why_gone(me, me, probe_process) is None
    info = probe_process(me.pid)
    assert info is not None and info.start_time == me.start_time and not info.ended

    child = subprocess.Popen([sys.executable, "-c", "pass"])
    child_owner = replace(me, pid=child.pid, start_time=None)
    deadline = time.monotonic() + 10
    while (info := probe_process(child.pid)) is not None and not info.ended:
        assert time.monotonic() < deadline, "the child never exited"
        time.sleep(0.01)
    # Exited but not reaped: still in the process table, yet it can write nothing more.
    assert why_gone(child_owner, me, probe_process) == "the process has exited"
    child.wait()
    assert probe_process(child.pid) is None
    assert why_gone(child_owner, me, probe_process) == "the process no longer exists"


def _open_runs(db_path: Path, owners: dict[str, RunOwner]) -> dict[str, int]:
    """One open run per serial, each as the process ``owners`` names left it.

    Written behind the store's back: each of those processes, beginning its
    run through a store, would already have judged the others' runs.
    """
    ref, text = _recipe()
    Store(db_path).close()
    conn = _raw(db_path)
    ids: dict[str, int] = {}
    try:
        conn.execute("INSERT OR IGNORE INTO recipes VALUES (?, 'default', '1.0', ?, ?)",
                     (ref.sha256, text, utc_iso(T0)))
        for serial, owner in owners.items():
            cursor = conn.execute(
                "INSERT INTO runs (serial, kind, recipe_name, recipe_version, recipe_sha256, "
                "station_id, operator, software_version, bench, started_at, owner) "
                "VALUES (?, 'calibrate', 'default', '1.0', ?, 1, 'alice', '0.1.0', 'sim', ?, ?)",
                (serial, ref.sha256, utc_iso(T0), owner.to_json()),
            )
            assert cursor.lastrowid is not None
            ids[serial] = cursor.lastrowid
        conn.commit()
    finally:
        conn.close()
    return ids


def test_the_next_run_finishes_runs_whose_station_is_gone_and_no_other(
    db_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    owners = {
        "SN1": _owner(DEAD_PID),
        "SN2": _owner(LIVE_PID),
        "SN3": _owner(DEAD_PID, host="line3-b"),
        "SN4": _owner(DEAD_PID + 1, boot="an-earlier-boot"),
        "SN5": _owner(REUSED_PID),
        "SN6": _owner(STATION_PID, start=900),  # this process's own open run
    }
    ids = _open_runs(db_path, owners)
    with Store(db_path, owner=HERE, probe=_process_table) as store:
        new = _begin(store, _run("SN7"))
        assert new.run_id is not None
        marked = {found.serial: found for found in store.interrupted}
        assert set(marked) == {"SN1", "SN4", "SN5"}
        for serial, found in marked.items():
            run = store.get_run(ids[serial])
            assert run.verdict is Verdict.ABORTED and run.finished_at is not None
            assert run.reason == found.reason
            owner = owners[serial]
            assert owner is not None
            assert run.reason.startswith(
                f"interrupted: station process {owner.pid} on host {HOST} ended without "
                "finishing the run (")
            assert run.reason.endswith(f"found at the start of run {new.run_id})")
            assert store.open_run_owner(ids[serial]) is None
        assert "the machine has restarted since" in marked["SN4"].reason
        assert "its pid now belongs to another process" in marked["SN5"].reason
        for serial in ("SN2", "SN3", "SN6"):
            assert store.get_run(ids[serial]).verdict is None
            assert store.open_run_owner(ids[serial]) == owners[serial]
        assert store.open_run_owner(new.run_id) == HERE
        # A later start finds nothing more to do: the rest may still be running.
        _begin(store, _run("SN8"))
        assert len(store.interrupted) == 3
    warnings = [r.getMessage() for r in caplog.records if r.levelname == "WARNING"]
    assert sum("marked aborted: interrupted" in w for w in warnings) == 3


def test_an_open_run_finished_as_interrupted_cannot_be_finished_again(db_path: Path) -> None:
    (run_id,) = _open_runs(db_path, {"SN1": _owner(DEAD_PID)}).values()
    with Store(db_path, owner=HERE, probe=_process_table) as store:
        _begin(store, _run("SN2"))
        record = store.get_run(run_id)
        with pytest.raises(FrozenRecord, match="finished record"):
            record.verdict = Verdict.PASS  # the record read back refuses first
        # A copy made to look unfinished-then-passed: the database refuses it too.
        late = dataclasses.replace(record, verdict=Verdict.PASS, finished_at=T0,
                                   reason="the old process came back?")
        with pytest.raises(DatabaseError, match="append-only"):
            store.finish_run(late)
        assert store.get_run(run_id).verdict is Verdict.ABORTED


def test_an_unreadable_owner_leaves_the_run_open(db_path: Path) -> None:
    assert RunOwner.from_json("{not json") is None
    assert RunOwner.from_json('["host", 1]') is None
    assert RunOwner.from_json('{"host": "h", "pid": "12"}') is None
    assert RunOwner.from_json(None) is None
    owner = _owner(DEAD_PID)
    assert RunOwner.from_json(owner.to_json()) == owner


# -- migration 0002 on a database already in use ---------------------------------------


def _version_1(tmp_path: Path) -> Path:
    """The shipped schema as it stood at version 1 (0001 only)."""
    first = load_migrations(files(MIGRATIONS_PACKAGE))[0]
    return _write_migrations(tmp_path / "v1", {first.name: first.sql})


def test_migration_0002_keeps_every_row_and_protects_the_old_ones(
    tmp_path: Path, db_path: Path
) -> None:
    Store(db_path, migrations=_version_1(tmp_path)).close()
    assert _user_version(db_path) == 1
    ref, text = _recipe()
    conn = _raw(db_path)  # software of version 1 wrote these rows
    try:
        conn.execute("INSERT INTO recipes VALUES (?, 'default', '1.0', ?, 'then')",
                     (ref.sha256, text))
        for serial, verdict in (("SN1", "pass"), ("SN2", None)):
            conn.execute(
                "INSERT INTO runs (serial, kind, recipe_name, recipe_version, recipe_sha256, "
                "station_id, operator, software_version, bench, started_at, verdict) "
                "VALUES (?, 'calibrate', 'default', '1.0', ?, 1, 'alice', '0.0.9', 'sim', ?, ?)",
                (serial, ref.sha256, utc_iso(T0), verdict),
            )
        conn.execute("INSERT INTO limit_checks (run_id, name, position, unit, passed) "
                     "VALUES (1, 'offset_a_mA', 0, 'mA', 1)")
        conn.commit()
    finally:
        conn.close()
    before = _snapshot(db_path)

    with Store(db_path, owner=HERE, probe=_process_table) as store:
        assert store.schema_version == len(load_migrations(files(MIGRATIONS_PACKAGE)))
        (old_pass,) = store.history("SN1")
        assert old_pass.run_uuid is None  # recorded before runs had one (0003)
        assert old_pass.verdict is Verdict.PASS and len(old_pass.limits) == 1
        # The open run of version 1 has no owner: nothing proves its station stopped.
        _begin(store, _run("SN3"))
        assert store.interrupted == []
        assert store.history("SN2")[0].verdict is None
        assert store.open_run_owner(2) is None
    after = _snapshot(db_path)
    # The owner (0002) and run_uuid (0003) columns added, empty on the old rows.
    assert [row[:-2] for row in after["runs"][:2]] == before["runs"]
    assert [row[-2:] for row in after["runs"][:2]] == [(None, None), (None, None)]
    assert {k: v for k, v in after.items() if k != "runs"} == {
        k: v for k, v in before.items() if k != "runs"}
    conn = _raw(db_path)
    try:
        with pytest.raises(sqlite3.IntegrityError, match="append-only"):
            conn.execute("DELETE FROM runs WHERE run_id = 1")
    finally:
        conn.close()


def test_a_run_keeps_the_uuid_it_was_created_with_and_no_two_runs_share_one(
    store: Store, db_path: Path
) -> None:
    run = _run("SN1")
    assert run.run_uuid is not None
    _begin(store, run)
    (back,) = store.history("SN1")
    assert back.run_uuid == run.run_uuid
    twin = _run("SN2")
    twin.run_uuid = run.run_uuid
    with pytest.raises(DatabaseError, match="UNIQUE"):
        _begin(store, twin)
    assert [r.serial for r in store.query(RunFilter())] == ["SN1"]
    conn = _raw(db_path)
    try:
        with pytest.raises(sqlite3.IntegrityError, match="append-only"):
            conn.execute("UPDATE runs SET run_uuid = 'x' WHERE run_id = 1")
    finally:
        conn.close()


# -- queries cannot be turned into SQL ---------------------------------------------------

_INJECTIONS = [
    "x' OR '1'='1",
    "'; DROP TABLE runs; --",
    "SN1' --",
    '" OR ""="',
    "%",
    "SN1'; DELETE FROM runs WHERE '1'='1",
]


@pytest.mark.parametrize("text", _INJECTIONS)
def test_query_filters_are_values_never_sql(store: Store, db_path: Path, text: str) -> None:
    with store:
        runs = _populate(store)
        assert store.query(RunFilter(serial=text)) == []
        assert store.query(RunFilter(recipe=text)) == []
        assert store.history(text) == []
        assert store.last_stored(text) is None
        assert store.verifications(text) == []
        assert store.recipe_text(text) is None
        assert [run.run_id for run in store.query(RunFilter())] == [r.run_id for r in runs]
    assert {"runs", "recipes", "limit_checks", "verifications"} <= _tables(db_path)


# -- paths that cannot hold a database ----------------------------------------------------


def _unprivileged() -> bool:
    """Root (with its capabilities) writes through any permission bits."""
    return os.geteuid() != 0


def test_a_directory_is_refused_as_a_database_path(tmp_path: Path) -> None:
    with pytest.raises(DatabasePathError, match="is a directory") as error:
        Store(tmp_path)
    assert str(tmp_path) in str(error.value)
    assert error.value.exit_code is ExitCode.USAGE


def test_a_file_where_the_folder_should_be_is_refused(tmp_path: Path) -> None:
    blocker = tmp_path / "results"
    blocker.write_text("not a folder")
    for path in (blocker / "station.db", blocker / "deeper" / "station.db"):
        with pytest.raises(DatabasePathError) as error:
            Store(path)
        assert str(path) in str(error.value)
        assert error.value.exit_code is ExitCode.USAGE
    assert blocker.read_text() == "not a folder"


@pytest.mark.skipif(not _unprivileged(), reason="root writes through permission bits")
def test_a_read_only_folder_or_file_is_refused(tmp_path: Path) -> None:
    folder = tmp_path / "ro"
    folder.mkdir()
    Store(folder / "existing.db").close()
    folder.chmod(0o555)
    try:
        for name in ("new.db", "existing.db"):
            with pytest.raises(DatabasePathError, match="not writable") as error:
                Store(folder / name)
            assert str(folder / name) in str(error.value)
        assert not (folder / "new.db").exists()
    finally:
        folder.chmod(0o755)
    readonly = tmp_path / "readonly.db"
    Store(readonly).close()
    readonly.chmod(0o444)
    with pytest.raises(DatabasePathError, match="not readable and writable"):
        Store(readonly)


def test_a_corrupt_database_is_a_station_error_and_is_left_untouched(tmp_path: Path) -> None:
    path = tmp_path / "station.db"
    garbage = b"SQLite format 2\x00" + bytes(range(256)) * 16
    path.write_bytes(garbage)
    with pytest.raises(DatabaseError) as error:
        Store(path)
    assert not isinstance(error.value, DatabasePathError)
    assert error.value.exit_code is ExitCode.STATION
    assert str(path) in str(error.value)
    assert path.read_bytes() == garbage


# -- a finished run is a record ---------------------------------------------------------


def test_a_finished_run_read_back_is_a_frozen_record_with_its_recipe_s_text(
    db_path: Path,
) -> None:
    with Store(db_path, owner=HERE, probe=_process_table) as store:
        first = _record(store, _run())
        full = _full_run(first.run_id or 0)
        _begin(store, full)
        store.finish_run(full)
        still_open = _begin(store, _run("SN2"))
        record = store.get_run(full.run_id or 0)
        assert not store.get_run(still_open.run_id or 0).frozen  # the procedure's to fill
    assert record.frozen and record == full
    _, text = _recipe()
    assert record.recipe.text == text and record.recipe == full.recipe
    for change in (lambda: setattr(record, "verdict", Verdict.PASS),
                   lambda: record.warnings.append("later"),
                   lambda: record.warnings.__setitem__(0, "edited"),
                   lambda: (record.fit or {})["h1"].update(r2=1.0),
                   lambda: (record.fit or {})["points"].append(4)):
        with pytest.raises(FrozenRecord):
            change()
    assert record == full  # nothing changed
    # Copied and pickled whole (process pools, reports), and still frozen.
    for copy in (pickle.loads(pickle.dumps(record)), copy_module.deepcopy(record)):
        assert copy == record and copy.frozen
    with pytest.raises(ValueError, match="not finished"):
        _run("SN3").freeze()
