"""A line's central results database on a real PostgreSQL server (a throwaway cluster
of the session, on loopback): the same records as a station's SQLite file, the same
append-only rules enforced by the server, many stations at once."""

from __future__ import annotations

import dataclasses
import json
import threading
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path
from typing import Any

import psycopg
import pytest
from typer.testing import CliRunner

from station.cli import app
from station.core import Trims
from station.errors import DatabaseError
from station.pgstore import PostgresStore
from station.rows import RunFilter, VerificationRecord
from station.runs import Run, Verdict
from station.storage import Backend, backend_of, describe, open_store, target_of
from station.store import Store
from tests.test_store import (
    DEAD_PID,
    HERE,
    T0,
    _begin,
    _finish,
    _full_run,
    _owner,
    _process_table,
    _record,
    _run,
)


@pytest.fixture
def pg(postgresql_url: str) -> Iterator[PostgresStore]:
    with PostgresStore(postgresql_url, owner=HERE, probe=_process_table) as store:
        yield store


def _raw(url: str) -> psycopg.Connection[Any]:
    """A client behind the store's back (psql, a script), committing each statement."""
    return psycopg.connect(url, autocommit=True)


def test_a_run_reads_back_from_postgresql_exactly_as_from_sqlite(
    pg: PostgresStore, tmp_path: Path,
) -> None:
    with Store(tmp_path / "station.db", owner=HERE, probe=_process_table) as lite:
        for store in (pg, lite):
            first = _record(store, _run())
            full = _full_run(first.run_id or 0)
            _begin(store, full)
            store.finish_run(full)
        from_pg, from_lite = pg.history("SN1"), lite.history("SN1")
    assert len(from_pg) == len(from_lite) == 2
    for a, b in zip(from_pg, from_lite, strict=True):
        # Each database gave the run its own number and the run its own identity.
        assert dataclasses.replace(a, run_uuid=None) == dataclasses.replace(b, run_uuid=None)
    assert from_pg[1].limits == _full_run(1).limits
    assert from_pg[1].started_at == T0


def test_the_server_refuses_every_change_to_a_finished_record(
    pg: PostgresStore, postgresql_url: str,
) -> None:
    _record(pg, _run())
    open_run = _begin(pg, _run("SN2"))
    statements = [
        "UPDATE runs SET reason = 'tidied' WHERE run_id = 1",
        "DELETE FROM runs WHERE run_id = 1",
        f"UPDATE runs SET serial = 'SN9' WHERE run_id = {open_run.run_id}",
        "TRUNCATE runs CASCADE",
        "UPDATE recipes SET text = 'x'",
        "DELETE FROM recipes",
        "INSERT INTO limit_checks (run_id, name, position, unit) VALUES (1, 'late', 9, '')",
    ]
    with _raw(postgresql_url) as conn:
        for sql in statements:
            with pytest.raises(psycopg.errors.RaiseException, match="append-only"):
                conn.execute(sql)
        # The open run can still be finished, once.
    _finish(pg, open_run)
    with pytest.raises(DatabaseError, match="append-only"):
        _finish(pg, open_run)
    assert [r.verdict for r in pg.query(RunFilter())] == [Verdict.PASS, Verdict.PASS]


def test_a_run_forwarded_twice_is_recorded_once(pg: PostgresStore) -> None:
    run = _begin(pg, _run())
    again = dataclasses.replace(run, run_id=None)
    with pytest.raises(DatabaseError, match="run_uuid"):
        _begin(pg, again)
    assert len(pg.history("SN1")) == 1


def test_qa_sees_the_whole_line_and_filters_it_by_station(pg: PostgresStore) -> None:
    for i, (serial, station) in enumerate((("SN1", 1), ("SN2", 2), ("SN1", 2), ("SN3", 3))):
        _record(pg, _run(serial, station_id=station, started_at=T0 + timedelta(hours=i)),
                Verdict.FAIL if serial == "SN3" else Verdict.PASS)
    assert [r.station_id for r in pg.history("SN1")] == [1, 2]
    assert [r.serial for r in pg.query(RunFilter(station_id=2))] == ["SN2", "SN1"]
    assert [r.serial for r in pg.query(RunFilter(verdict=Verdict.FAIL))] == ["SN3"]
    since = pg.query(RunFilter(since=T0 + timedelta(hours=1), until=T0 + timedelta(hours=2)))
    assert [r.serial for r in since] == ["SN2", "SN1"]
    assert [r.serial for r in pg.query(RunFilter(limit=2))] == ["SN1", "SN3"]
    last = pg.last_stored("SN1")
    assert last is not None and last.station_id == 2  # recalibrated elsewhere: found here


def test_a_run_whose_station_process_died_is_finished_as_aborted_by_the_next(
    postgresql_url: str,
) -> None:
    with PostgresStore(postgresql_url, owner=_owner(DEAD_PID), probe=_process_table) as dead:
        orphan = _begin(dead, _run("SN1"))
    with PostgresStore(postgresql_url, owner=HERE, probe=_process_table) as here:
        _begin(here, _run("SN2"))
        assert [i.run_id for i in here.interrupted] == [orphan.run_id]
        (found,) = here.history("SN1")
    assert found.verdict is Verdict.ABORTED and found.reason is not None
    assert found.reason.startswith(f"interrupted: station process {DEAD_PID}")


def test_many_stations_begin_and_finish_runs_at_once(postgresql_url: str) -> None:
    errors: list[BaseException] = []

    def station(number: int) -> None:
        try:
            with PostgresStore(postgresql_url, owner=HERE, probe=_process_table) as store:
                for k in range(5):
                    _record(store, _run(f"SN{number}{k}", station_id=number))
        except BaseException as exc:  # every failure is reported by the assertion below
            errors.append(exc)

    threads = [threading.Thread(target=station, args=(n,)) for n in range(1, 5)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=120)
    assert not errors, errors
    with PostgresStore(postgresql_url) as store:
        runs = store.query(RunFilter())
        assert store.schema_version == 1
    assert len(runs) == 20 and len({r.run_uuid for r in runs}) == 20
    assert sorted(r.run_id or 0 for r in runs) == list(range(1, 21))


def test_verifications_and_recipes_are_kept_on_the_line(pg: PostgresStore) -> None:
    run = _record(pg, _run())
    record = VerificationRecord("SN1", T0, 2, "bob", "sim", True, Trims(1.0, 2.0, 9990.0, 10010.0),
                                run.run_id, Trims(1.0, 2.0, 9990.0, 10010.0))
    pg.add_verification(record)
    assert pg.verifications("SN1") == [record]
    assert pg.recipe_text(run.recipe.sha256) is not None


def test_a_database_of_newer_software_is_refused_untouched(postgresql_url: str) -> None:
    PostgresStore(postgresql_url).close()
    with _raw(postgresql_url) as conn:
        conn.execute("INSERT INTO schema_migrations (version, name) VALUES (99, 'future')")
    with pytest.raises(DatabaseError, match="schema version 99 is newer"):
        PostgresStore(postgresql_url)


def test_an_unreachable_server_is_a_database_error_without_the_password(
    postgresql_cluster: Any,
) -> None:
    url = f"postgresql://qa:secret@127.0.0.1:{postgresql_cluster.port + 1}/line"
    with pytest.raises(DatabaseError) as caught:
        open_store(url)
    assert "secret" not in str(caught.value)
    assert "postgresql://qa@127.0.0.1" in str(caught.value)


def test_a_location_names_its_backend() -> None:
    assert backend_of(target_of("postgresql://u@h/db")) is Backend.POSTGRESQL
    assert backend_of(target_of("postgres://h/db")) is Backend.POSTGRESQL
    assert backend_of(target_of("~/station.db")) is Backend.SQLITE
    assert isinstance(target_of("~/station.db"), Path)
    assert describe("postgresql://u:pw@h:5432/db") == "postgresql://u@h:5432/db"
    assert describe("postgresql://h/db") == "postgresql://h/db"


def test_calibrate_history_and_stats_run_against_the_line_s_database(
    postgresql_url: str, station_home: Path,
) -> None:
    runner = CliRunner()
    done = runner.invoke(app, ["calibrate", "SN123", "--db", postgresql_url, "--json"])
    assert done.exit_code == 0, done.output
    doc = json.loads(done.stdout)
    assert doc["verdict"] == "pass"
    # The recording stays on the station's disk; the record holds its hash.
    recording = Path(doc["recording"])
    assert recording.is_file() and station_home in recording.parents
    history = runner.invoke(app, ["history", "SN123", "--db", postgresql_url, "--json"])
    assert history.exit_code == 0, history.output
    (run,) = json.loads(history.stdout)
    assert run["verdict"] == "pass" and run["recording_sha256"] == doc["recording_sha256"]
    stats = runner.invoke(app, ["stats", "--db", postgresql_url, "--json"])
    assert stats.exit_code == 0, stats.output
    with PostgresStore(postgresql_url) as store:
        (stored,) = store.history("SN123")
    assert isinstance(stored, Run) and stored.trims_stored
