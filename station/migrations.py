"""The numbered SQL migrations a results database's schema is built from.

``NNNN_name.sql`` files, numbered 1, 2, 3... without gaps, shipped as package data
(``db`` for a station's SQLite file, ``db/postgresql`` for a line's database); each
store applies those its database lacks, in order, one transaction each. See
``db/README.md``, "The migration rule".
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from importlib.resources.abc import Traversable
from typing import Final

from station.errors import DatabaseError

MIGRATIONS_PACKAGE: Final = "db"
"""Where the shipped migrations live (package data, so they work installed)."""

_MIGRATION_FILE = re.compile(r"^(?P<number>\d{4})_[a-z0-9_]+\.sql$")


@dataclass(frozen=True)
class Migration:
    """One schema step: ``number`` is the ``user_version`` it leaves behind."""

    number: int
    name: str
    sql: str


def load_migrations(source: Traversable) -> tuple[Migration, ...]:
    """Read ``NNNN_name.sql`` files, numbered 1, 2, 3... without gaps.

    A gap or a misnamed ``.sql`` file is a packaging mistake; skipping it would
    leave every database a step behind without anyone noticing.
    """
    found: list[Migration] = []
    for entry in source.iterdir():
        if not entry.name.endswith(".sql"):
            continue
        match = _MIGRATION_FILE.match(entry.name)
        if match is None:
            raise DatabaseError(str(source), f"migration {entry.name!r} is not named NNNN_name.sql")
        found.append(Migration(int(match["number"]), entry.name, entry.read_text("utf-8")))
    found.sort(key=lambda migration: migration.number)
    numbers = [migration.number for migration in found]
    if numbers != list(range(1, len(found) + 1)):
        raise DatabaseError(str(source), f"migrations must be numbered 1..n, found {numbers}")
    return tuple(found)
