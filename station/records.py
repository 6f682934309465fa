"""What QA and the spool's forwarding do: read runs, sum them, forward them.

Apart from ``station.service`` because none of it touches a bench: ``station
history`` and ``station stats`` start without importing the procedure, the
drivers or the bus libraries.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, cast

from station.errors import InputError
from station.rows import RunFilter
from station.serials import parse_serial
from station.storage import Backend, DbTarget, backend_of, describe, open_store, target_of

if TYPE_CHECKING:
    from station.pgstore import PostgresStore
    from station.qa import RecipeStatistics
    from station.runs import Run
    from station.spool import Forwarded


def history(db_path: DbTarget, serial_label: str, *, station_id: int | None = None
            ) -> list[Run]:
    """Every run of one unit, oldest first; only those of one station with ``station_id``."""
    serial = parse_serial(serial_label)
    with open_store(db_path) as store:
        if station_id is None:
            return store.history(serial.label)
        return store.query(RunFilter(serial=serial.label, station_id=station_id))


def query(db_path: DbTarget, run_filter: RunFilter) -> list[Run]:
    with open_store(db_path) as store:
        return store.query(run_filter)


def statistics(db_path: DbTarget, run_filter: RunFilter) -> list[RecipeStatistics]:
    """Mean, standard deviation and Cpk of trims and residual ripple, per recipe version.

    Capability is judged against the limits the runs themselves were judged by: each
    record keeps its limit checks with their bounds. No recipe text is parsed again, so
    runs recorded under an older recipe format (or a key since renamed) still count.
    Only runs that measured a unit (pass or fail) count; errors and aborts measured
    nothing. The database does the sums (``station.statsql``): a line's million runs are
    never fetched.
    """
    with open_store(db_path) as store:
        return store.statistics(run_filter)


# --- a spool's forwarding ---------------------------------------------------------------


@dataclass(frozen=True)
class SyncReport:
    """What ``station sync`` forwarded to the line's database, and what still waits."""

    line: str
    forwarded: list[Forwarded]
    waiting: list[Run]


def sync(db: DbTarget, *, list_only: bool = False, source: Path | None = None) -> SyncReport:
    """Forward this station's spool to its line's database (``station sync``), or only
    list what waits (``--list``, which needs no connection). ``source`` forwards another
    SQLite database instead: a station's own history from before it joined the line."""
    if backend_of(db) is not Backend.POSTGRESQL:
        raise InputError("station sync forwards this station's spool to its line's database: "
                         "--db (or STATION_DB) must name it as a postgresql:// URL")
    from station import spool  # noqa: PLC0415 - psycopg only for a line's database

    if source is not None:
        if not source.is_file():
            raise InputError(f"--from {source}: no such database file")
        if backend_of(target_of(str(source))) is not Backend.SQLITE:
            raise InputError(f"--from {source}: a station's SQLite file is imported")
    path = source or spool.spool_path()
    if not path.exists():
        return SyncReport(describe(db), [], [])
    if list_only:
        return SyncReport(describe(db), [], spool.pending(path))
    from station.store import Store  # noqa: PLC0415 - the spool is a station's SQLite file

    with open_store(db) as line, Store(path) as spooled:
        done = spool.forward(spooled, cast("PostgresStore", line))
        waiting = spooled.unforwarded()
    return SyncReport(describe(db), done, waiting)
