"""A line's central results database on PostgreSQL (psycopg 3).

The same tables, columns and append-only rules as a station's SQLite file
(``db/postgresql``; the server's triggers refuse every change to a finished record,
for every client), the same ``Run`` records back (``station.rows``), and the same
interrupted-run check: each open run names the process that began it, and the next run
begun on the same host finishes as aborted the runs whose process is provably gone
(``why_gone``); a run begun on another host is that host's to judge. Many stations write
at once: beginning a run, and a schema's first migration, are serialised by transaction
advisory locks, and every read is one snapshot. Every psycopg failure surfaces as a
``DatabaseError`` naming the database without its password.
"""

from __future__ import annotations

import logging
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import replace
from datetime import UTC, datetime
from importlib.resources import files
from importlib.resources.abc import Traversable
from types import TracebackType
from typing import Any, Final, Self
from uuid import UUID

import psycopg
from psycopg.rows import RowMaker

from station.errors import DatabaseError, DatabaseRefused, DatabaseUnreachable, InputError
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
from station.storage import describe

log = logging.getLogger(__name__)

MIGRATIONS_FOLDER: Final = "postgresql"
"""The PostgreSQL schema's migrations, within the ``db`` package."""
CONNECT_TIMEOUT_S: Final = 5
"""How long a station waits for the line's server before calling it unreachable."""
_REFUSALS: Final = ("password authentication failed", "no pg_hba.conf entry",
                     "does not exist", "authentication failed", "permission denied")
"""What a server that answered says when the station's URL is wrong (libpq gives no
SQLSTATE for a failed connection, only the server's words); anything else, a server
starting up or shutting down among them, is an outage."""
_MIGRATION_LOCK: Final = 0x5354_4D47  # "STMG": one migrator at a time
_BEGIN_LOCK: Final = 0x5354_5255  # "STRU": one run begun at a time (the interrupted check)

# Booleans are 0/1 in SQLite and in the shared row mapping; PostgreSQL's are boolean.
_BOOLEAN_COLUMNS: Final = frozenset({"trims_stored", "passed", "trims_match"})
# Unquoted names fold to lower case in PostgreSQL: rows are read back under the schema's.
_CANONICAL: Final = {name.lower(): name for name in (
    *START_COLUMNS, *RESULT_COLUMNS, *LIMIT_COLUMNS, *VERIFICATION_COLUMNS,
    "run_id", "owner", "verification_id", "text")}


def _plain(value: object) -> object:
    """A value as the shared row mapping reads it (times as ``utc_iso`` text)."""
    if isinstance(value, datetime):
        return utc_iso(value)
    if isinstance(value, UUID):
        return str(value)
    return value


def _rows(cursor: psycopg.Cursor[Any]) -> RowMaker[dict[str, Any]]:
    names = [_CANONICAL.get(c.name, c.name) for c in cursor.description or ()]

    def make(values: Sequence[Any]) -> dict[str, Any]:
        return {name: _plain(v) for name, v in zip(names, values, strict=True)}

    return make


def _sql_values(values: dict[str, object]) -> dict[str, object]:
    """Lower-case keys (the placeholders' names) and PostgreSQL's booleans."""
    return {key.lower(): (None if value is None else bool(value)) if key in _BOOLEAN_COLUMNS
            else value for key, value in values.items()}


def _insert(table: str, columns: Sequence[str], tail: str = "") -> str:
    names = [c.lower() for c in columns]
    return (f"INSERT INTO {table} ({', '.join(names)}) "
            f"VALUES ({', '.join(f'%({n})s' for n in names)}){tail}")


_INSERT_RECIPE = _insert("recipes", ("sha256", "name", "version", "text", "first_used_at"),
                         " ON CONFLICT (sha256) DO NOTHING")
_INSERT_RUN = _insert("runs", (*START_COLUMNS, "owner"), " RETURNING run_id")
_ASSIGN_RESULTS = ", ".join(f"{c.lower()} = %({c.lower()})s" for c in RESULT_COLUMNS)
_UPDATE_RESULTS = f"UPDATE runs SET {_ASSIGN_RESULTS} WHERE run_id = %(run_id)s"
_SELECT_OPEN_RUNS = "SELECT run_id, serial, owner FROM runs WHERE verdict IS NULL ORDER BY run_id"
_FINISH_INTERRUPTED = (
    "UPDATE runs SET verdict = %(verdict)s, reason = %(reason)s, finished_at = %(finished_at)s "
    "WHERE run_id = %(run_id)s AND verdict IS NULL")
_INSERT_LIMIT = _insert("limit_checks", LIMIT_COLUMNS)
_INSERT_VERIFICATION = _insert("verifications", VERIFICATION_COLUMNS,
                               " RETURNING verification_id")
_SELECT_LIMITS = (f"SELECT {', '.join(c.lower() for c in LIMIT_COLUMNS)} FROM limit_checks "
                  "WHERE run_id = ANY(%s) ORDER BY run_id, position")
_CREATE_VERSIONS = (
    "CREATE TABLE IF NOT EXISTS schema_migrations (version integer PRIMARY KEY, "
    "name text NOT NULL, applied_at timestamptz NOT NULL DEFAULT now())")


class PostgresStore:
    """An open connection to a line's results database; close it (or use ``with``).

    ``migrations``, ``owner`` and ``probe`` stand in for the shipped schema, this
    process and this machine's process table, as in ``station.store.Store``.
    """

    def __init__(self, url: str, *, migrations: Traversable | None = None,
                 owner: RunOwner | None = None, probe: ProcessProbe = probe_process) -> None:
        self.url = url
        self._owner = owner
        self._probe = probe
        self.interrupted: list[InterruptedRun] = []
        source = migrations or files(MIGRATIONS_PACKAGE).joinpath(MIGRATIONS_FOLDER)
        known = load_migrations(source)
        try:
            conn = psycopg.connect(url, connect_timeout=CONNECT_TIMEOUT_S, row_factory=_rows)
        except psycopg.OperationalError as exc:
            message = " ".join(str(exc).split())
            if any(words in message for words in _REFUSALS):
                raise DatabaseRefused(self.location, f"the server refused the station: "
                                      f"{message}") from exc
            raise DatabaseUnreachable(self.location, f"cannot connect: {message}") from exc
        except psycopg.Error as exc:
            raise self._error("cannot connect", exc) from exc
        try:
            self._prepare(conn, known)
        except BaseException:
            conn.close()
            raise
        self._conn: psycopg.Connection[dict[str, Any]] | None = conn

    # -- lifetime --------------------------------------------------------------

    @property
    def location(self) -> str:
        return describe(self.url)

    @property
    def closed(self) -> bool:
        return self._conn is None

    def close(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            conn.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None:
        self.close()

    @property
    def schema_version(self) -> int:
        with self._transaction("read the schema version") as conn:
            return _version(conn)

    # -- runs ------------------------------------------------------------------

    def begin_run(self, run: Run, recipe_text: str) -> int:
        """As ``Store.begin_run``: committed at once, with this process as its owner."""
        if run.run_id is not None:
            raise ValueError(f"run of {run.serial} already begun as run {run.run_id}")
        recipe = recipe_values(run, recipe_text)
        owner = self._owner if self._owner is not None else current_owner()
        with self._transaction(f"begin a run of {run.serial}") as conn:
            # Judged before this run exists and while no other station begins one.
            conn.execute("SELECT pg_advisory_xact_lock(%s)", (_BEGIN_LOCK,))
            gone = gone_owners(conn.execute(_SELECT_OPEN_RUNS).fetchall(), owner,
                               self._probe)
            conn.execute(_INSERT_RECIPE, recipe)
            row = conn.execute(_INSERT_RUN, _sql_values(
                {**start_values(run), "owner": owner.to_json()})).fetchone()
            if row is None:  # pragma: no cover - RETURNING always gives the row
                raise self._error("begin a run", None)
            run_id = int(row["run_id"])
            interrupted = interrupted_runs(gone, run_id)
            finished_at = utc_iso(datetime.now(UTC))
            for found in interrupted:
                conn.execute(_FINISH_INTERRUPTED, found.finish_values(finished_at))
        log_interrupted(interrupted)
        self.interrupted.extend(interrupted)
        run.run_id = run_id
        return run_id

    def finish_run(self, run: Run) -> None:
        """As ``Store.finish_run``: everything the run learnt, atomically and once."""
        check_finishable(run)
        with held(), self._transaction(f"finish run {run.run_id}") as conn:
            exists = conn.execute("SELECT 1 FROM runs WHERE run_id = %s", (run.run_id,))
            if exists.fetchone() is None:
                raise InputError(f"no run {run.run_id} in database {self.location}")
            self._finish_row(conn, run)

    def forward_run(self, run: Run, recipe_text: str, previous_uuid: UUID | None
                    ) -> tuple[int, bool]:
        """Record a finished run another database kept (a station's spool), once.

        Keyed by the run's UUID: a run already here (forwarded before, its spool not told
        so because the station stopped in between) is not recorded again. Its previous
        run is found here by UUID too, the spool's own numbers meaning nothing here.
        Returns this database's number for the run and whether it was new.
        """
        if run.run_uuid is None or run.verdict is None or run.finished_at is None:
            raise ValueError(f"run of {run.serial}: only a finished run with a UUID is "
                             "forwarded")
        recipe = recipe_values(run, recipe_text)
        with held(), self._transaction(f"forward a run of {run.serial}") as conn:
            found = conn.execute("SELECT run_id, verdict FROM runs WHERE run_uuid = %s",
                                 (run.run_uuid,)).fetchone()
            if found is not None and found["verdict"] is not None:
                return int(found["run_id"]), False
            if found is not None:
                # Begun here, finished in the spool while this server was away: finished
                # now, on the row that holds its beginning (and its previous run).
                run_id = int(found["run_id"])
                self._finish_row(conn, replace(run, run_id=run_id))
                return run_id, True
            previous = None if previous_uuid is None else conn.execute(
                "SELECT run_id FROM runs WHERE run_uuid = %s", (previous_uuid,)).fetchone()
            here = replace(run, previous_run_id=None if previous is None
                           else int(previous["run_id"]))
            conn.execute(_INSERT_RECIPE, recipe)
            row = conn.execute(_INSERT_RUN, _sql_values(
                {**start_values(here), "owner": None})).fetchone()
            if row is None:  # pragma: no cover - RETURNING always gives the row
                raise self._error("forward a run", None)
            run_id = int(row["run_id"])
            self._finish_row(conn, replace(here, run_id=run_id))
        return run_id, True

    @staticmethod
    def _finish_row(conn: psycopg.Connection[dict[str, Any]], run: Run) -> None:
        """An open row's limit checks (admitted only while it is open), then its results."""
        assert run.run_id is not None
        with conn.cursor() as cursor:
            cursor.executemany(_INSERT_LIMIT, [_sql_values(limit_values(run.run_id, i, check))
                                               for i, check in enumerate(run.limits)])
        conn.execute(_UPDATE_RESULTS, _sql_values(result_values(run)))

    def get_run(self, run_id: int) -> Run:
        runs = self._runs(f"read run {run_id}", "WHERE run_id = %s", (run_id,))
        if not runs:
            raise InputError(f"no run {run_id} in database {self.location}")
        return runs[0]

    def history(self, serial: str) -> list[Run]:
        """Every run of one unit at every station of the line, oldest first."""
        return self._runs(f"read the history of {serial}", "WHERE serial = %s ORDER BY run_id",
                          (serial,))

    def query(self, f: RunFilter) -> list[Run]:
        where, params = filter_clauses(f, "%s")
        if f.limit is None:
            return self._runs("query runs", f"{where} ORDER BY run_id", params)
        newest = self._runs("query runs", f"{where} ORDER BY run_id DESC LIMIT %s",
                            [*params, f.limit])
        return newest[::-1]

    def statistics(self, f: RunFilter) -> list[RecipeStatistics]:
        """QA's figures per recipe version, summed by the database in one snapshot."""
        with self._transaction("compute the statistics") as conn:
            conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
            return recipe_statistics(lambda sql, params: conn.execute(sql, params).fetchall(),
                                     f, "%s")

    def last_stored(self, serial: str) -> Run | None:
        """The run whose trims the unit should hold, whichever station stored them."""
        runs = self._runs(f"find the stored trims of {serial}",
                          "WHERE serial = %s AND trims_stored ORDER BY run_id DESC LIMIT 1",
                          (serial,))
        return runs[0] if runs else None

    def open_run_owner(self, run_id: int) -> RunOwner | None:
        with self._transaction(f"read the owner of run {run_id}") as conn:
            row = conn.execute("SELECT verdict, owner FROM runs WHERE run_id = %s",
                               (run_id,)).fetchone()
        if row is None:
            raise InputError(f"no run {run_id} in database {self.location}")
        return None if row["verdict"] is not None else RunOwner.from_json(row["owner"])

    def recipe_text(self, sha256: str) -> str | None:
        with self._transaction(f"read recipe {sha256}") as conn:
            row = conn.execute("SELECT text FROM recipes WHERE sha256 = %s",
                               (sha256,)).fetchone()
        return None if row is None else str(row["text"])

    # -- verifications ---------------------------------------------------------

    def add_verification(self, v: VerificationRecord) -> int:
        with held(), self._transaction(f"record a verification of {v.serial}") as conn:
            row = conn.execute(_INSERT_VERIFICATION,
                               _sql_values(verification_values(v))).fetchone()
        if row is None:  # pragma: no cover - RETURNING always gives the row
            raise self._error("record a verification", None)
        return int(row["verification_id"])

    def verifications(self, serial: str) -> list[VerificationRecord]:
        with self._transaction(f"read the verifications of {serial}") as conn:
            rows = conn.execute("SELECT * FROM verifications WHERE serial = %s "
                                "ORDER BY verification_id", (serial,)).fetchall()
        return [verification_from(row) for row in rows]

    # -- plumbing --------------------------------------------------------------

    def _error(self, doing: str, exc: BaseException | None) -> DatabaseError:
        detail = "" if exc is None else f": {str(exc).strip()}"
        return DatabaseError(self.location, f"{doing}{detail}")

    def _prepare(self, conn: psycopg.Connection[dict[str, Any]],
                 known: Sequence[Migration]) -> None:
        """Apply the migrations this database lacks, each in one transaction, one station
        at a time; a database written by newer software is refused untouched."""
        newest = known[-1].number if known else 0
        try:
            with conn.transaction():
                conn.execute("SELECT pg_advisory_xact_lock(%s)", (_MIGRATION_LOCK,))
                conn.execute(_CREATE_VERSIONS)
                version = _version(conn)
                if version > newest:
                    raise self._error(
                        f"schema version {version} is newer than this software knows "
                        f"({newest}); refusing it, install the newer station software", None)
                for migration in known:
                    if migration.number > version:
                        with conn.transaction():
                            conn.execute(migration.sql.encode("utf-8"))
                            conn.execute("INSERT INTO schema_migrations (version, name) "
                                         "VALUES (%s, %s)", (migration.number, migration.name))
        except psycopg.Error as exc:
            raise self._error("cannot prepare the schema (rolled back)", exc) from exc

    @contextmanager
    def _transaction(self, doing: str) -> Iterator[psycopg.Connection[dict[str, Any]]]:
        """One transaction, rolled back on any error; psycopg's errors become ours."""
        conn = self._conn
        if conn is None:
            raise self._error(f"cannot {doing}: the store is closed", None)
        try:
            with conn.transaction():
                yield conn
        except psycopg.Error as exc:
            if conn.broken or conn.closed:  # the server went away, not the request wrong
                raise DatabaseUnreachable(self.location, f"cannot {doing}: "
                                          f"{str(exc).strip()}") from exc
            raise self._error(f"cannot {doing}", exc) from exc

    def _runs(self, doing: str, tail: str, params: Sequence[object]) -> list[Run]:
        with self._transaction(doing) as conn:
            # One snapshot for the runs and their limit checks, whoever writes meanwhile.
            conn.execute("SET TRANSACTION ISOLATION LEVEL REPEATABLE READ")
            rows = conn.execute(f"{SELECT_RUNS} {tail}", params).fetchall()
            ids = [row["run_id"] for row in rows]
            limits: dict[int, list[LimitCheck]] = {run_id: [] for run_id in ids}
            if ids:
                for row in conn.execute(_SELECT_LIMITS, (ids,)):
                    limits[row["run_id"]].append(limit_from(row))
        return [run_from(row, limits[row["run_id"]]) for row in rows]


def _version(conn: psycopg.Connection[dict[str, Any]]) -> int:
    row = conn.execute("SELECT coalesce(max(version), 0) AS version "
                       "FROM schema_migrations").fetchone()
    return 0 if row is None else int(row["version"])
