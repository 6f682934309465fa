"""The results database keeps every run whole, migrates safely, and answers QA.

Runs are the station's traceability: a field lost on the way to SQLite, a
migration half-applied, or a file held open after the station is done with it
would each surface months later on the line, so they are tested here.
"""

from __future__ import annotations

import hashlib
import math
import sqlite3
import threading
from collections.abc import Callable, Iterator
from dataclasses import fields, replace
from datetime import UTC, datetime, timedelta, timezone
from importlib.resources import files
from pathlib import Path

import pytest

from station.core import Trims
from station.errors import DatabaseError, ExitCode, InputError
from station.runs import LimitCheck, LimitName, RecipeRef, Ripple, Run, RunKind, Verdict
from station.store import MIGRATIONS_PACKAGE, RunFilter, Store, VerificationRecord, load_migrations

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


def _begin(store: Store, run: Run) -> Run:
    _, text = _recipe(run.recipe.name, run.recipe.version)
    store.begin_run(run, text)
    return run


def _record(store: Store, run: Run, verdict: Verdict = Verdict.PASS, *, stored: bool = True) -> Run:
    """Begin and finish ``run`` as the procedure would, with every result filled in."""
    _begin(store, run)
    run.verdict = verdict
    run.finished_at = run.started_at + timedelta(seconds=93.5)
    run.trims_stored = stored
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
        with pytest.raises(InputError, match="no run 99"):
            store.finish_run(ghost)


def test_nan_estimate_comes_back_as_nan_not_as_missing_trims(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        run.trims_estimated = Trims(math.nan, 1.0, 10000.0, 10000.0)
        store.finish_run(run)
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
        store.finish_run(run)
        assert run.run_id is not None
        back = store.get_run(run.run_id)
        assert back.limits == checks
        assert back.failed_limits == (checks[2],)


def test_finishing_again_replaces_the_limit_checks(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        run.limits = (LimitCheck(LimitName.OFFSET_A, 1.0, -5.0, 5.0, "mA", True),)
        store.finish_run(run)
        run.limits = (LimitCheck(LimitName.OFFSET_B, 9.0, -5.0, 5.0, "mA", False),)
        store.finish_run(run)
        assert run.run_id is not None
        assert store.get_run(run.run_id).limits == run.limits


def test_a_limit_checked_twice_is_refused_and_nothing_changes(store: Store) -> None:
    with store:
        run = _begin(store, _run())
        check = LimitCheck(LimitName.OFFSET_A, 1.0, -5.0, 5.0, "mA", True)
        run.limits = (check, check)
        run.verdict = Verdict.PASS
        with pytest.raises(ValueError, match="twice"):
            store.finish_run(run)
        assert run.run_id is not None
        assert store.get_run(run.run_id).verdict is None  # the failed finish changed nothing


def test_limits_of_many_runs_each_go_to_their_own_run(store: Store) -> None:
    with store:
        for i in range(30):
            run = _begin(store, _run(f"SN{i % 3}"))
            run.limits = (LimitCheck(LimitName.OFFSET_A, float(i), -50.0, 50.0, "mA", True),)
            store.finish_run(run)
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
