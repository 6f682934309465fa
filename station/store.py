"""The station's SQLite results database (a line's PostgreSQL: ``station.pgstore``).

A run becomes a row the moment it begins and is committed at once, so a
station that dies mid-run still leaves a trace (verdict NULL); the results
then fill the row's open fields in one transaction, once: finished runs, their
limit checks, verifications and recipe texts are append-only, enforced by
SQLite triggers (``db/0002_append_only.sql``) for every connection. Each open
run names its owner process (host, boot, pid, start time), so the next run to
begin can finish as ``aborted`` the runs whose process provably died
(``kill -9``, power loss) and leave alone those still running elsewhere.

The schema is the numbered migrations of the ``db`` package, applied in order
on first use; a database written by newer software is refused rather than
half-understood. Every sqlite3 failure surfaces as a ``DatabaseError`` naming
the file, so the CLI can say which disk to look at; a path that cannot hold a
database at all (a directory, an unwritable folder, a read-only file) is a
``DatabasePathError``, the operator's input error, found before anything runs.
"""

from __future__ import annotations

import json
import logging
import os
import sqlite3
import time
from collections.abc import Iterator, Sequence
from contextlib import contextmanager, suppress
from datetime import UTC, datetime
from importlib.resources import files
from importlib.resources.abc import Traversable
from pathlib import Path
from types import TracebackType
from typing import Self

from station.errors import DatabaseError, DatabasePathError, InputError
from station.migrations import MIGRATIONS_PACKAGE, Migration, load_migrations
from station.owners import (
    InterruptedRun,
    ProcessProbe,
    RunOwner,
    current_owner,
    gone_owners,
    interrupted_runs,
    log_interrupted,
    probe_process,
)
from station.qa import RecipeStatistics
from station.rows import (
    LIMIT_COLUMNS,
    RESULT_COLUMNS,
    SELECT_RUNS,
    START_COLUMNS,
    VERIFICATION_COLUMNS,
    RunFilter,
    VerificationRecord,
    check_finishable,
    filter_clauses,
    limit_from,
    limit_values,
    recipe_values,
    result_values,
    run_from,
    start_values,
    verification_from,
    verification_values,
)
from station.runs import LimitCheck, Run, utc_iso
from station.signals import held
from station.statsql import recipe_statistics

log = logging.getLogger(__name__)


BUSY_TIMEOUT_MS = 5000
"""Several stations may share one database file: wait this long for a lock."""
ANALYSIS_LIMIT = 1000
"""Rows ``PRAGMA optimize`` samples per index: enough to rank them, in milliseconds."""


def _insert(table: str, columns: Sequence[str], verb: str = "INSERT") -> str:
    return (
        f"{verb} INTO {table} ({', '.join(columns)}) "
        f"VALUES ({', '.join(':' + column for column in columns)})"
    )


# The same recipe text is stored once, however many runs follow it.
_INSERT_RECIPE = _insert(
    "recipes", ("sha256", "name", "version", "text", "first_used_at"), "INSERT OR IGNORE"
)
# The owner is the store's, not the run's: it says which process wrote the row.
_INSERT_RUN = _insert("runs", (*START_COLUMNS, "owner"))
_UPDATE_RESULTS = (
    f"UPDATE runs SET {', '.join(f'{c} = :{c}' for c in RESULT_COLUMNS)} WHERE run_id = :run_id"
)
# Served by the partial index runs_open: the open runs, however many finished ones there are.
_SELECT_OPEN_RUNS = "SELECT run_id, serial, owner FROM runs WHERE verdict IS NULL ORDER BY run_id"
_FINISH_INTERRUPTED = (
    "UPDATE runs SET verdict = :verdict, reason = :reason, finished_at = :finished_at "
    "WHERE run_id = :run_id AND verdict IS NULL"
)
_INSERT_LIMIT = _insert("limit_checks", LIMIT_COLUMNS)
_INSERT_VERIFICATION = _insert("verifications", VERIFICATION_COLUMNS)
# One query for the limits of any number of runs: the ids travel as one JSON array.
_SELECT_LIMITS = (
    f"SELECT {', '.join(LIMIT_COLUMNS)} FROM limit_checks "
    "WHERE run_id IN (SELECT value FROM json_each(?)) ORDER BY run_id, position"
)


# -- the store ----------------------------------------------------------------------

# sqlite3 primary result codes that mean "this path cannot hold a database here",
# as opposed to "this file is damaged" (NOTADB, CORRUPT), a station fault.
_PATH_ERRORS = frozenset({
    sqlite3.SQLITE_CANTOPEN, sqlite3.SQLITE_READONLY, sqlite3.SQLITE_PERM, sqlite3.SQLITE_AUTH,
})


class Store:
    """An open results database; close it (or use ``with``) to release the file.

    ``migrations`` replaces the shipped ``db`` package as the schema source, so
    tests can feed broken or future migrations. ``owner`` and ``probe`` replace
    this process and this machine's process table in the interrupted-run check,
    so tests can play other processes, hosts and boots.
    """

    def __init__(
        self,
        path: Path,
        *,
        migrations: Traversable | None = None,
        owner: RunOwner | None = None,
        probe: ProcessProbe = probe_process,
    ) -> None:
        self.path = Path(path)
        self._conn: sqlite3.Connection | None = None
        self._owner = owner
        self._probe = probe
        self.interrupted: list[InterruptedRun] = []
        """Runs this store found interrupted and finished as aborted, oldest first."""
        known = load_migrations(migrations if migrations is not None else files(MIGRATIONS_PACKAGE))
        self._check_path()
        try:
            # isolation_level=None: the store, not the sqlite3 module, opens transactions.
            conn = sqlite3.connect(self.path, isolation_level=None, timeout=BUSY_TIMEOUT_MS / 1000)
        except sqlite3.Error as exc:
            raise self._open_error(exc) from exc
        try:
            self._prepare(conn, known)
        except BaseException:
            conn.close()
            raise
        self._conn = conn

    # -- lifetime --------------------------------------------------------------

    @property
    def location(self) -> str:
        """The database as messages name it."""
        return str(self.path)

    @property
    def closed(self) -> bool:
        return self._conn is None

    def close(self) -> None:
        # Forgotten before closing, so a second close is a no-op even if this one fails.
        conn, self._conn = self._conn, None
        if conn is not None:
            _optimize(conn)
            try:
                conn.close()
            except sqlite3.Error as exc:
                raise self._error("cannot close", exc) from exc

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self.close()

    @property
    def schema_version(self) -> int:
        with self._transaction("read the schema version") as conn:
            return _user_version(conn)

    # -- runs ------------------------------------------------------------------

    def begin_run(self, run: Run, recipe_text: str) -> int:
        """Record that ``run`` started, with the exact recipe text; set ``run.run_id``.

        Committed before returning: if the station dies during the motion, the
        row (verdict NULL, its owner this process) is what tells the next shift
        a run never finished. In the same transaction, open runs whose owner
        process is provably gone are finished as ``aborted`` (see ``why_gone``);
        they are logged, and kept in ``self.interrupted``.
        """
        if run.run_id is not None:
            raise ValueError(f"run of {run.serial} already begun as run {run.run_id}")
        recipe = recipe_values(run, recipe_text)
        owner = self._owner if self._owner is not None else current_owner()
        # Not held(): a stop arriving during this transaction rolls it back to nothing begun.
        with self._transaction(f"begin a run of {run.serial}", write=True) as conn:
            # Judged before this run exists, under the write lock, so no other station
            # can begin or finish a run in between.
            gone = gone_owners(conn.execute(_SELECT_OPEN_RUNS).fetchall(), owner, self._probe)
            conn.execute(_INSERT_RECIPE, recipe)
            run_id = conn.execute(
                _INSERT_RUN, {**start_values(run), "owner": owner.to_json()}
            ).lastrowid
            if run_id is None:  # pragma: no cover - sqlite3 always sets it after an INSERT
                raise self._error("begin a run", None)
            interrupted = interrupted_runs(gone, run_id)
            finished_at = utc_iso(datetime.now(UTC))
            for found in interrupted:
                conn.execute(_FINISH_INTERRUPTED, found.finish_values(finished_at))
        log_interrupted(interrupted)
        self.interrupted.extend(interrupted)
        run.run_id = run_id
        return run_id

    def finish_run(self, run: Run) -> None:
        """Write everything the run learnt, and its limit checks, atomically and once.

        A finished run is final: finishing it again is refused by the
        database's triggers (``DatabaseError``), so a record QA has seen never
        changes behind its back. Hence a verdict and a finishing time are
        required; a run that is still going has nothing to finish.
        """
        check_finishable(run)
        assert run.run_id is not None  # checked
        values = result_values(run)
        limits = [limit_values(run.run_id, i, check) for i, check in enumerate(run.limits)]
        # held(): a stop signal arriving now waits for the commit, so the run is recorded whole.
        with held(), self._transaction(f"finish run {run.run_id}", write=True) as conn:
            exists = conn.execute("SELECT 1 FROM runs WHERE run_id = ?", (run.run_id,))
            if exists.fetchone() is None:
                raise InputError(f"no run {run.run_id} in database {self.path}")
            # Limit checks first: the triggers admit them only while the run is open.
            conn.executemany(_INSERT_LIMIT, limits)
            conn.execute(_UPDATE_RESULTS, values)

    def get_run(self, run_id: int) -> Run:
        runs = self._runs(f"read run {run_id}", "WHERE run_id = ?", (run_id,))
        if not runs:
            raise InputError(f"no run {run_id} in database {self.path}")
        return runs[0]

    def history(self, serial: str) -> list[Run]:
        """Every run of one unit, oldest first."""
        return self._runs(
            f"read the history of {serial}", "WHERE serial = ? ORDER BY run_id", (serial,)
        )

    def query(self, f: RunFilter) -> list[Run]:
        where, params = filter_clauses(f, "?")
        if f.limit is None:
            return self._runs("query runs", f"{where} ORDER BY run_id", params)
        # The newest come first out of SQLite (so LIMIT keeps them), then back in order.
        newest = self._runs(
            "query runs", f"{where} ORDER BY run_id DESC LIMIT ?", [*params, f.limit]
        )
        return newest[::-1]

    def statistics(self, f: RunFilter) -> list[RecipeStatistics]:
        """QA's figures per recipe version, summed by the database in one snapshot."""
        with self._transaction("compute the statistics") as conn:
            return recipe_statistics(lambda sql, params: conn.execute(sql, params).fetchall(),
                                     f, "?")

    def last_stored(self, serial: str) -> Run | None:
        """The run whose trims the unit should hold: the latest that stored any."""
        runs = self._runs(
            f"find the stored trims of {serial}",
            "WHERE serial = ? AND trims_stored = 1 ORDER BY run_id DESC LIMIT 1",
            (serial,),
        )
        return runs[0] if runs else None

    def open_run_owner(self, run_id: int) -> RunOwner | None:
        """Who began ``run_id`` and has not finished it; None once finished or if unknown."""
        with self._transaction(f"read the owner of run {run_id}") as conn:
            row = conn.execute("SELECT verdict, owner FROM runs WHERE run_id = ?",
                               (run_id,)).fetchone()
        if row is None:
            raise InputError(f"no run {run_id} in database {self.path}")
        return None if row["verdict"] is not None else RunOwner.from_json(row["owner"])

    def recipe_text(self, sha256: str) -> str | None:
        with self._transaction(f"read recipe {sha256}") as conn:
            row = conn.execute("SELECT text FROM recipes WHERE sha256 = ?", (sha256,)).fetchone()
        return None if row is None else str(row["text"])

    # -- a spool's forwarding ---------------------------------------------------

    def unforwarded(self) -> list[Run]:
        """Finished runs not yet forwarded to a line's database, in the order they began
        (a spool's backlog; an open run waits until it is finished)."""
        return self._runs(
            "read the runs to forward",
            "WHERE verdict IS NOT NULL AND run_id NOT IN (SELECT run_id FROM forwarded) "
            "ORDER BY run_id", ())

    def mark_forwarded(self, run_id: int, destination: str, destination_run_id: int) -> None:
        """Note, once, that ``run_id`` now lives at ``destination`` as its number there."""
        with held(), self._transaction(f"note run {run_id} as forwarded", write=True) as conn:
            conn.execute(
                "INSERT INTO forwarded (run_id, forwarded_at, destination, destination_run_id) "
                "VALUES (?, ?, ?, ?)",
                (run_id, utc_iso(datetime.now(UTC)), destination, destination_run_id))

    # -- verifications ---------------------------------------------------------

    def add_verification(self, v: VerificationRecord) -> int:
        values = verification_values(v)
        with held(), self._transaction(f"record a verification of {v.serial}",
                                       write=True) as conn:
            verification_id = conn.execute(_INSERT_VERIFICATION, values).lastrowid
        if verification_id is None:  # pragma: no cover - always set after an INSERT
            raise self._error("record a verification", None)
        return verification_id

    def verifications(self, serial: str) -> list[VerificationRecord]:
        """Every verification of one unit, oldest first."""
        with self._transaction(f"read the verifications of {serial}") as conn:
            rows = conn.execute(
                "SELECT * FROM verifications WHERE serial = ? ORDER BY verification_id",
                (serial,),
            ).fetchall()
        return [verification_from(row) for row in rows]

    # -- plumbing --------------------------------------------------------------

    def _error(self, doing: str, exc: BaseException | None) -> DatabaseError:
        return DatabaseError(str(self.path), doing if exc is None else f"{doing}: {exc}")

    def _path_error(self, problem: str) -> DatabasePathError:
        return DatabasePathError(str(self.path), f"cannot hold the results database: {problem}")

    def _open_error(self, exc: sqlite3.Error) -> DatabaseError:
        """Opening failed: the path's fault (exit 2) or the file's (exit 3).

        SQLite cannot open or write there (permissions, read-only file or
        medium): the operator named a place that cannot hold a database. The
        file is there but is not a database, or is damaged: that is the
        station's data in trouble, for a technician, and the file is left
        untouched (never "repaired" by recreating it).
        """
        code = getattr(exc, "sqlite_errorcode", None)
        if isinstance(code, int) and code & 0xFF in _PATH_ERRORS:
            return self._path_error(str(exc))
        return self._error("cannot open", exc)

    def _check_path(self) -> None:
        """Refuse, before SQLite creates anything, a path that cannot hold the database.

        SQLite's own message for all of these is "unable to open database
        file", which names neither the path nor the problem. The database's
        folder must be writable even when the file exists, because SQLite keeps
        the ``-wal`` and ``-shm`` files beside it.
        """
        path, folder = self.path, self.path.parent
        try:
            if path.is_dir():
                raise self._path_error("it is a directory")
            if folder.exists() and not folder.is_dir():
                raise self._path_error(f"{folder} is a file, not a directory")
            try:
                folder.mkdir(parents=True, exist_ok=True)
            except OSError as exc:
                raise self._path_error(
                    f"cannot create its directory {folder}: {exc.strerror or exc}"
                ) from exc
            if not os.access(folder, os.W_OK | os.X_OK):
                raise self._path_error(
                    f"directory {folder} is not writable (SQLite keeps the -wal and -shm "
                    "files beside the database)"
                )
            if path.exists():
                if not path.is_file():
                    raise self._path_error("it is not a regular file")
                if not os.access(path, os.R_OK | os.W_OK):
                    raise self._path_error("the file is not readable and writable")
        except OSError as exc:  # stat itself refused, e.g. a folder that cannot be searched
            raise self._path_error(exc.strerror or str(exc)) from exc

    def _prepare(self, conn: sqlite3.Connection, known: Sequence[Migration]) -> None:
        conn.row_factory = sqlite3.Row
        newest = known[-1].number if known else 0
        try:
            # Both are per connection, not stored in the file: set on every open.
            conn.execute("PRAGMA foreign_keys = ON")
            conn.execute(f"PRAGMA busy_timeout = {BUSY_TIMEOUT_MS}")
            version = _user_version(conn)
            # Checked before WAL is switched on: a newer database is not even touched.
            if version > newest:
                raise self._error(
                    f"schema version {version} is newer than this software knows "
                    f"({newest}); refusing it, install the newer station software",
                    None,
                )
            mode = _switch_to_wal(conn)
        except sqlite3.Error as exc:
            raise self._open_error(exc) from exc
        if mode.lower() != "wal":
            # SQLite keeps the old mode when it cannot switch (read-only medium, a file it
            # may not write): without WAL, readers would meet "database is locked".
            raise self._path_error(f"SQLite cannot use its write-ahead log there "
                                   f"(journal mode stays {mode!r})")
        for migration in known:
            if migration.number > version:
                version = self._apply(conn, migration)

    def _apply(self, conn: sqlite3.Connection, migration: Migration) -> int:
        """Run one migration and its version bump as one transaction; return the version.

        IMMEDIATE takes the write lock first, so two stations opening a new
        file together queue up; the loser's statements then fail on tables that
        exist, and the version it finds afterwards shows the work is done.
        """
        script = (
            f"BEGIN IMMEDIATE;\n{migration.sql}\n;\n"
            f"PRAGMA user_version = {migration.number};\nCOMMIT;"
        )
        try:
            conn.executescript(script)
        except BaseException as exc:
            if conn.in_transaction:
                with suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
            if not isinstance(exc, sqlite3.Error):
                raise
            try:
                version = _user_version(conn)
            except sqlite3.Error:
                version = -1
            if version >= migration.number:
                return version
            raise self._error(
                f"migration {migration.name} failed and was rolled back "
                f"(schema stays at version {version}): {exc}",
                None,
            ) from exc
        return migration.number

    @contextmanager
    def _transaction(self, doing: str, *, write: bool = False) -> Iterator[sqlite3.Connection]:
        """One transaction, rolled back on any error; sqlite3's errors become ours.

        Reads take one too, so a run and its limit checks come from the same
        snapshot even while another station writes.
        """
        conn = self._conn
        if conn is None:
            raise self._error(f"cannot {doing}: the store is closed", None)
        try:
            # A writer takes the lock up front: upgrading a read lock later can fail at once
            # with SQLITE_BUSY instead of waiting out the busy timeout.
            conn.execute("BEGIN IMMEDIATE" if write else "BEGIN")
            yield conn
            conn.execute("COMMIT")
        except BaseException as exc:
            if conn.in_transaction:
                with suppress(sqlite3.Error):
                    conn.execute("ROLLBACK")
            if isinstance(exc, sqlite3.Error):
                raise self._error(f"cannot {doing}", exc) from exc
            raise

    def _runs(self, doing: str, tail: str, params: Sequence[object]) -> list[Run]:
        with self._transaction(doing) as conn:
            rows = conn.execute(f"{SELECT_RUNS} {tail}", params).fetchall()
            ids = [row["run_id"] for row in rows]
            # Limit checks of all these runs in one query, grouped here by run.
            limits: dict[int, list[LimitCheck]] = {run_id: [] for run_id in ids}
            if ids:
                for row in conn.execute(_SELECT_LIMITS, (json.dumps(ids),)):
                    limits[row["run_id"]].append(limit_from(row))
        return [run_from(row, limits[row["run_id"]]) for row in rows]


# -- rows <-> dataclasses ---------------------------------------------------------


def _optimize(conn: sqlite3.Connection) -> None:
    """Refresh the planner's statistics of the tables this connection read, as SQLite
    advises on closing. Without them it cannot tell a serial (a dozen runs) from a recipe
    (a million) and may read a whole index for a unit's statistics. Sampling keeps it to
    milliseconds; a station that cannot get the write lock at once leaves it to the next."""
    with suppress(sqlite3.Error):
        conn.execute(f"PRAGMA analysis_limit = {ANALYSIS_LIMIT}")
        conn.execute("PRAGMA busy_timeout = 50")
        conn.execute("PRAGMA optimize")


def _switch_to_wal(conn: sqlite3.Connection) -> str:
    """Ask for the write-ahead log; return the journal mode SQLite settled on.

    WAL: QA reads while a station writes, and a killed station leaves the file whole.
    Switching needs the file to itself, and SQLite reports "locked" at once instead
    of waiting when another station is opening the same new file at that instant, so
    the switch is retried for as long as any other statement would wait.
    """
    deadline = time.monotonic() + BUSY_TIMEOUT_MS / 1000
    while True:
        try:
            return str(conn.execute("PRAGMA journal_mode = WAL").fetchone()[0])
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) and "busy" not in str(exc):
                raise
            if time.monotonic() > deadline:
                raise
            time.sleep(0.02)


def _user_version(conn: sqlite3.Connection) -> int:
    return int(conn.execute("PRAGMA user_version").fetchone()[0])


