"""A line's central results database on a real PostgreSQL server (a throwaway cluster
of the session, on loopback): the same records as a station's SQLite file, the same
append-only rules enforced by the server, many stations at once."""

from __future__ import annotations

import dataclasses
import re
import sys
import threading
from collections.abc import Iterator
from datetime import timedelta
from importlib.resources import files
from pathlib import Path
from typing import Any

import psycopg
import pytest

from station.cli import main
from station.core import Trims
from station.errors import DatabaseError, DatabaseUnreachable
from station.migrations import MIGRATIONS_PACKAGE, load_migrations
from station.pgstore import MIGRATIONS_FOLDER, PostgresStore
from station.records import history
from station.rows import RunFilter, VerificationRecord
from station.runs import Run, RunKind, Verdict
from station.spool import forward, note_reached, pending
from station.storage import Backend, backend_of, describe, open_store, target_of
from station.store import Store
from station.testing.postgres import Cluster
from tests.test_calibrate import LAST_STDERR
from tests.test_calibrate import _run as _cli
from tests.test_store import (
    DEAD_PID,
    HERE,
    T0,
    _begin,
    _finish,
    _full_run,
    _owner,
    _process_table,
    _recipe,
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


def test_qa_sees_the_whole_line_and_filters_it_by_station(
    pg: PostgresStore, postgresql_url: str,
) -> None:
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
    assert [r.station_id for r in history(postgresql_url, "SN1")] == [1, 2]
    assert [r.station_id for r in history(postgresql_url, "SN1", station_id=2)] == [2]


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
        # Four stations migrating one new database at once: each migration once.
        newest = load_migrations(files(MIGRATIONS_PACKAGE) / MIGRATIONS_FOLDER)[-1].number
        assert store.schema_version == newest
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
    postgresql_cluster: Cluster,
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
    postgresql_url: str, station_home: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, doc = _cli(["calibrate", "SN123", "--db", postgresql_url, "--json"], monkeypatch,
                     capsys)
    assert code == 0 and doc["verdict"] == "pass", LAST_STDERR[0]
    # The recording stays on the station's disk; the record holds its hash.
    recording = Path(doc["recording"])
    assert recording.is_file() and station_home in recording.parents
    code, runs = _cli(["history", "SN123", "--db", postgresql_url, "--json"], monkeypatch,
                      capsys)
    assert code == 0, LAST_STDERR[0]
    (run,) = runs
    assert run["verdict"] == "pass" and run["recording_sha256"] == doc["recording_sha256"]
    code, stats = _cli(["stats", "--db", postgresql_url, "--json"], monkeypatch, capsys)
    assert code == 0 and stats[0]["runs"] == 1, LAST_STDERR[0]
    with PostgresStore(postgresql_url) as store:
        (stored,) = store.history("SN123")
    assert isinstance(stored, Run) and stored.trims_stored


# -- a station whose line database does not answer --------------------------------------


def _lost_line(cluster: Cluster) -> str:
    """A line database this station recorded into before, which nobody answers for now
    (the cluster's port plus one, on loopback): an outage."""
    url = f"postgresql://station:pw@127.0.0.1:{cluster.port + 1}/line"
    note_reached(describe(url))
    return url


def test_a_line_never_reached_or_refusing_the_station_is_refused_before_the_bench_moves(
    postgresql_cluster: Cluster, station_home: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    mistyped = f"postgresql://station:pw@127.0.0.1:{postgresql_cluster.port + 1}/line"
    wrong_role = postgresql_cluster.url().replace("station@", "nobody@")
    wrong_database = postgresql_cluster.url("no_such_line")
    for url, words in ((mistyped, "never reached it"), (wrong_role, 'role "nobody"'),
                       (wrong_database, 'database "no_such_line"')):
        code, out = _cli(["calibrate", "SN123", "--db", url, "--json"], monkeypatch, capsys)
        assert code == 2 and out is None, url
        assert words in LAST_STDERR[0] and ":pw@" not in LAST_STDERR[0]
    # Nothing recorded anywhere, no spool, the unit never touched.
    assert not (station_home / "spool.db").exists() and not (station_home / "recordings").exists()
    # Once reached, the same URL going silent is an outage: the run is spooled.
    note_reached(describe(mistyped))
    code, doc = _cli(["calibrate", "SN123", "--db", mistyped, "--json"], monkeypatch, capsys)
    assert code == 0 and any("spool" in w for w in doc["warnings"]), LAST_STDERR[0]


def test_a_station_that_cannot_reach_its_line_spools_and_sync_forwards_once(
    postgresql_cluster: Cluster, postgresql_url: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def cli(*args: str) -> tuple[int, Any]:
        return _cli(list(args), monkeypatch, capsys)

    dead = _lost_line(postgresql_cluster)
    code, first = cli("calibrate", "SN123", "--db", dead, "--json")
    assert code == 0 and first["verdict"] == "pass", LAST_STDERR[0]
    assert any("recorded in this station's spool" in w and ":pw@" not in w
               for w in first["warnings"])
    # Named as the spool numbers it: the line's run 1 of this unit may be on this disk too.
    assert Path(first["recording"]).name == "SN123-spool000001.blf"
    # Field service at the same station while the line is still away: the spool has it.
    code, _ = cli("recalibrate", "SN123", "--reason", "noisy", "--db", dead, "--json")
    assert code == 0, LAST_STDERR[0]
    assert len(pending()) == 2
    code, listed = cli("sync", "--list", "--db", postgresql_url, "--json")
    assert code == 0 and [r["kind"] for r in listed["waiting"]] == ["calibrate", "recalibrate"]
    # The line unreachable: sync says so (exit 3) and forwards nothing.
    code, _ = cli("sync", "--db", dead, "--json")
    assert code == 3 and "cannot connect" in LAST_STDERR[0] and len(pending()) == 2

    code, report = cli("sync", "--db", postgresql_url, "--json")
    assert code == 0, LAST_STDERR[0]
    assert [f["new"] for f in report["forwarded"]] == [True, True] and report["waiting"] == []
    with PostgresStore(postgresql_url) as line:
        calibration, service = line.history("SN123")
    assert (calibration.kind.value, service.kind.value) == ("calibrate", "recalibrate")
    assert service.previous_run_id == calibration.run_id  # found again by its UUID
    assert str(calibration.run_uuid) == report["forwarded"][0]["run_uuid"]
    # A second sync forwards nothing.
    code, twice = cli("sync", "--db", postgresql_url, "--json")
    assert code == 0 and twice["forwarded"] == []
    with PostgresStore(postgresql_url) as line:
        assert len(line.history("SN123")) == 2


def test_a_run_forwarded_before_its_station_stopped_is_not_forwarded_again(
    postgresql_url: str, tmp_path: Path,
) -> None:
    with Store(tmp_path / "spool.db") as spooled:
        _record(spooled, _run("SN1"))
        (run,) = spooled.unforwarded()
        with PostgresStore(postgresql_url) as line:
            # The line committed it; the station stopped before noting so in its spool.
            line_id, new = line.forward_run(run, _recipe_text(), None)
            assert new
            (again,) = forward(spooled, line)
            assert again.line_run_id == line_id and not again.new
            assert len(line.history("SN1")) == 1
        assert spooled.unforwarded() == []


def test_the_next_calibration_with_the_line_back_forwards_the_spool_first(
    postgresql_cluster: Cluster, postgresql_url: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    code, _ = _cli(["calibrate", "SN123", "--db", _lost_line(postgresql_cluster), "--json"],
                   monkeypatch, capsys)
    assert code == 0, LAST_STDERR[0]
    code, _ = _cli(["calibrate", "SN124", "--db", postgresql_url, "--json"], monkeypatch,
                   capsys)
    assert code == 0, LAST_STDERR[0]
    with PostgresStore(postgresql_url) as line:
        runs = line.query(RunFilter())
    assert [r.serial for r in runs] == ["SN123", "SN124"]  # in the order they began
    assert pending() == []


def test_sync_needs_a_line_database(monkeypatch: pytest.MonkeyPatch,
                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, _ = _cli(["sync", "--db", "station.db"], monkeypatch, capsys)
    assert code == 2 and "postgresql://" in LAST_STDERR[0]


def _recipe_text() -> str:
    return _recipe()[1]


def test_sync_shows_forwarded_runs_under_the_line_s_numbers(
    postgresql_cluster: Cluster, postgresql_url: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    with PostgresStore(postgresql_url) as line:
        _record(line, _run("SN9"))  # the line's run 1, from another station
    code, spooled = _cli(["calibrate", "SN123", "--db", _lost_line(postgresql_cluster),
                          "--json"], monkeypatch, capsys)
    assert code == 0 and spooled["run_id"] == 1, LAST_STDERR[0]
    warning = next(w for w in spooled["warnings"] if "spool" in w)
    assert "\n" not in warning and warning.count("postgresql://station@127.0.0.1") == 1
    monkeypatch.setattr(sys, "argv", ["station", "sync", "--db", postgresql_url])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code in (0, None)
    table = capsys.readouterr().out
    # The line's run 2, its serial under its number.
    assert re.search(r"^\s*2\s+\d{4}-\d\d-\d\d\s+pass.*\n\s*SN123\s", table, re.MULTILINE), table


def test_a_line_lost_while_the_run_went_on_has_its_run_finished_by_sync(
    postgresql_url: str, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    # The server answers when the run begins and is gone when it finishes.
    def gone(self: PostgresStore, run: Run) -> None:
        raise DatabaseUnreachable(self.location, "cannot finish run: server closed the "
                                  "connection unexpectedly")

    with monkeypatch.context() as patch:
        patch.setattr(PostgresStore, "finish_run", gone)
        code, doc = _cli(["calibrate", "SN123", "--db", postgresql_url, "--json"], monkeypatch,
                         capsys)
    assert code == 0 and doc["verdict"] == "pass", LAST_STDERR[0]
    assert any("when the run finished" in w for w in doc["warnings"])
    assert Path(doc["recording"]).name == "SN123-run000001.blf"  # the line's number
    with PostgresStore(postgresql_url) as line:
        (open_row,) = line.history("SN123")
    assert open_row.verdict is None and str(open_row.run_uuid) == doc["run_uuid"]
    assert [str(r.run_uuid) for r in pending()] == [doc["run_uuid"]]

    code, report = _cli(["sync", "--db", postgresql_url, "--json"], monkeypatch, capsys)
    assert code == 0, LAST_STDERR[0]
    assert [(f["line_run_id"], f["new"]) for f in report["forwarded"]] == [(1, True)]
    with PostgresStore(postgresql_url) as line:
        (finished,) = line.history("SN123")
    assert finished.run_id == 1 and finished.verdict is Verdict.PASS
    assert finished.trims_after is not None and finished.limits
    assert finished.recording == doc["recording"]


def test_a_station_s_own_history_is_imported_into_the_line_once(
    postgresql_url: str, tmp_path: Path, station_home: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    def cli(*args: str) -> tuple[int, Any]:
        return _cli(list(args), monkeypatch, capsys)

    own = tmp_path / "before-the-line.db"
    with Store(own, owner=HERE, probe=_process_table) as lite:
        _record(lite, _run("SN5"))
        legacy = _run("SN7", started_at=T0 + timedelta(minutes=1))
        legacy.run_uuid = None  # recorded before runs had a UUID of their own
        _record(lite, legacy)
        again = _run("SN7", started_at=T0 + timedelta(minutes=2), kind=RunKind.RECALIBRATE)
        again.previous_run_id = legacy.run_id
        _record(lite, again)
    copy = tmp_path / "copy.db"  # taken before the import: it knows nothing of it
    copy.write_bytes(own.read_bytes())
    code, listed = cli("sync", "--from", str(own), "--list", "--db", postgresql_url, "--json")
    assert code == 0 and [r["serial"] for r in listed["waiting"]] == ["SN5", "SN7", "SN7"]
    code, report = cli("sync", "--from", str(own), "--db", postgresql_url, "--json")
    assert code == 0, LAST_STDERR[0]
    assert [f["new"] for f in report["forwarded"]] == [True, True, True]
    with PostgresStore(postgresql_url) as line:
        before, after = line.history("SN7")
    assert before.run_uuid is not None and after.previous_run_id == before.run_id
    # Imported again: the file noted what it forwarded; a copy made before the import
    # offers every run again, and the line knows each by its UUID (derived or its own).
    code, twice = cli("sync", "--from", str(own), "--db", postgresql_url, "--json")
    assert code == 0 and twice["forwarded"] == [], LAST_STDERR[0]
    code, copied = cli("sync", "--from", str(copy), "--db", postgresql_url, "--json")
    assert code == 0 and [f["new"] for f in copied["forwarded"]] == [False] * 3
    with PostgresStore(postgresql_url) as line:
        assert len(line.query(RunFilter())) == 3
    for bad in (str(tmp_path / "missing.db"), postgresql_url):
        code, _ = cli("sync", "--from", bad, "--db", postgresql_url, "--json")
        assert code == 2, bad
