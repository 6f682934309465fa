"""Runs a station recorded while its line's database was out of reach, and forwarding them.

A station set to a line's PostgreSQL (``--db postgresql://…``) that cannot reach it does
not stop the line: it records the run into a SQLite spool of its own
(``$STATION_HOME/spool.db``, the station's usual schema) and says so in the run's
warnings. Once the server answers again, the next calibration, or ``station sync``,
forwards the spool's finished runs in the order they began, each exactly once: the line
knows a run by its UUID and refuses a second copy, and the spool notes each run it
forwarded (``db/0004_forwarded.sql``), so a station stopped half-way forwards the rest
the next time and nothing twice.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, replace
from pathlib import Path
from uuid import UUID, uuid5

from station.paths import station_home
from station.pgstore import PostgresStore
from station.runs import Run, utc_iso
from station.store import Store

log = logging.getLogger(__name__)

SPOOL_FILE = "spool.db"
REACHED_FILE = "lines-reached"
"""The line databases this station has recorded into, one (password-free) URL a line:
only one of those that stops answering is an outage; nothing answering at a URL never
reached is a wrong URL."""


def spool_path() -> Path:
    """Where this station keeps the runs its line's database has not seen yet."""
    return station_home() / SPOOL_FILE


@dataclass(frozen=True)
class Forwarded:
    """One spooled run, now in the line's database."""

    run: Run  # as the spool recorded it
    line_run_id: int  # its number in the line's database
    new: bool  # False: the line had it already (forwarded before the spool noted it)


def forward(spool: Store, line: PostgresStore) -> list[Forwarded]:
    """Forward every finished run the spool holds and the line has not seen, oldest first;
    each noted in the spool as soon as the line has committed it.

    The spool may also be a station's own database from before it joined the line
    (``station sync --from``): its runs older than run UUIDs get one derived from what
    identifies them, the same at every import, so none is recorded twice."""
    done: list[Forwarded] = []
    for run in spool.unforwarded():
        assert run.run_id is not None  # read back from the spool
        text = run.recipe.text  # read with the run: the record carries its recipe
        if text is None:  # the schema's foreign key keeps every run's recipe
            raise ValueError(f"spool run {run.run_id}: its recipe text is missing")
        known = replace(run, run_uuid=identity(run))
        line_id, new = line.forward_run(known, text, _previous_uuid(spool, run))
        spool.mark_forwarded(run.run_id, line.location, line_id)
        log.info("spooled run %d of %s forwarded as run %d of %s%s", run.run_id, run.serial,
                 line_id, line.location, "" if new else " (it was there already)")
        done.append(Forwarded(run, line_id, new))
    return done


_RUNS_BEFORE_UUIDS = UUID("6f1d3c52-6c1e-4c3e-9a53-0b6d2f1c7a10")
"""The namespace of the UUIDs derived for runs recorded before runs had their own."""


def identity(run: Run) -> UUID:
    """The run's UUID, or for a run recorded before runs had one, a UUID derived from
    the station, the unit, the moment it began and its number there."""
    if run.run_uuid is not None:
        return run.run_uuid
    return uuid5(_RUNS_BEFORE_UUIDS, f"{run.station_id}/{run.serial}/"
                 f"{utc_iso(run.started_at)}/{run.run_id}")


def _previous_uuid(spool: Store, run: Run) -> UUID | None:
    """The UUID of the run a recalibration followed, which the line knows it by."""
    if run.previous_run_id is None:
        return None
    return identity(spool.get_run(run.previous_run_id))


def note_reached(line: str) -> None:
    """Remember that this station reached the line database ``line`` (as ``describe``
    names it)."""
    if reached(line):
        return
    path = station_home() / REACHED_FILE
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("a", encoding="utf-8") as f:
        f.write(f"{line}\n")


def reached(line: str) -> bool:
    """Whether this station ever recorded into the line database ``line``."""
    try:
        known = (station_home() / REACHED_FILE).read_text(encoding="utf-8").splitlines()
    except FileNotFoundError:
        return False
    return line in known


def pending(spool_file: Path | None = None) -> list[Run]:
    """The spool's runs not yet forwarded (none without a spool)."""
    path = spool_file or spool_path()
    if not path.exists():
        return []
    with Store(path) as spool:
        return spool.unforwarded()
