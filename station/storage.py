"""Where a station's results go: a SQLite file of its own, or a line's PostgreSQL.

``--db`` (or ``STATION_DB``) names either a path, the station's own SQLite file, or a
``postgresql://`` URL, the line's central database that many stations write to at
once. Both backends keep the same tables under the same append-only rules and give
back the same ``Run`` records, so everything above this module (calibration, QA,
field service) is written against ``RunStore`` and never asks which it has. A backend
is imported only when a location names it, as python-can imports an interface's
module only when it is named: a station on its own file never loads psycopg.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable, Sequence
from enum import StrEnum
from pathlib import Path
from types import TracebackType
from typing import TYPE_CHECKING, Final, Protocol, Self

if TYPE_CHECKING:
    from station.owners import InterruptedRun, RunOwner
    from station.qa import RecipeStatistics
    from station.rows import RunFilter, VerificationRecord
    from station.runs import Run

DbTarget = Path | str
"""A SQLite file's path, or a PostgreSQL URL (text starting ``postgresql://``)."""


class Backend(StrEnum):
    """The database a location names."""

    SQLITE = "sqlite"
    POSTGRESQL = "postgresql"


_URL_SCHEMES: Final = ("postgresql://", "postgres://")
_BACKENDS: Final[dict[Backend, str]] = {
    Backend.SQLITE: "station.store:Store",
    Backend.POSTGRESQL: "station.pgstore:PostgresStore",
}
"""Each backend's store class, as module:class, imported on first use."""


class RunStore(Protocol):
    """What the station needs of a results database (see ``station.store.Store``)."""

    interrupted: list[InterruptedRun]

    @property
    def location(self) -> str: ...
    @property
    def closed(self) -> bool: ...
    def close(self) -> None: ...
    def __enter__(self) -> Self: ...
    def __exit__(self, exc_type: type[BaseException] | None, exc: BaseException | None,
                 traceback: TracebackType | None) -> None: ...
    @property
    def schema_version(self) -> int: ...
    def begin_run(self, run: Run, recipe_text: str) -> int: ...
    def finish_run(self, run: Run) -> None: ...
    def get_run(self, run_id: int) -> Run: ...
    def history(self, serial: str) -> list[Run]: ...
    def query(self, f: RunFilter) -> list[Run]: ...
    def statistics(self, f: RunFilter) -> list[RecipeStatistics]: ...
    def last_stored(self, serial: str) -> Run | None: ...
    def open_run_owner(self, run_id: int) -> RunOwner | None: ...
    def recipe_text(self, sha256: str) -> str | None: ...
    def add_verification(self, v: VerificationRecord) -> int: ...
    def verifications(self, serial: str) -> list[VerificationRecord]: ...


def is_url(text: str) -> bool:
    """Whether ``text`` names a PostgreSQL database rather than a file."""
    return text.startswith(_URL_SCHEMES)


def target_of(text: str) -> DbTarget:
    """``--db``'s text as a location: a URL stays text, anything else is a path."""
    return text if is_url(text) else Path(text).expanduser()


def backend_of(target: DbTarget) -> Backend:
    return Backend.POSTGRESQL if isinstance(target, str) and is_url(target) else Backend.SQLITE


def store_class(backend: Backend) -> Callable[[DbTarget], RunStore]:
    """The store class of ``backend`` (its module imported now, once)."""
    module, _, name = _BACKENDS[backend].partition(":")
    found: Callable[[DbTarget], RunStore] = getattr(importlib.import_module(module), name)
    return found


def open_store(target: DbTarget) -> RunStore:
    """The results database at ``target``, open (close it, or use ``with``)."""
    backend = backend_of(target)
    return store_class(backend)(target if backend is Backend.POSTGRESQL else Path(target))


def describe(target: DbTarget) -> str:
    """``target`` as messages name it: a URL without its password."""
    if isinstance(target, Path) or not is_url(target):
        return str(target)
    scheme, _, rest = target.partition("://")
    credentials, at, host = rest.rpartition("@")
    if not at:
        return target
    user = credentials.split(":", 1)[0]
    return f"{scheme}://{user}@{host}" if user else f"{scheme}://{host}"


__all__: Sequence[str] = (
    "Backend", "DbTarget", "RunStore", "backend_of", "describe", "is_url", "open_store",
    "store_class", "target_of",
)
