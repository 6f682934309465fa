"""The results' tables as the station's dataclasses: one mapping for every backend.

Both stores (``station.store``, SQLite; ``station.pgstore``, PostgreSQL) keep the same
columns and read rows back through these functions, so a run reads the same whichever
database holds it, and a column added for one is added for both. A row is any mapping
from column name to value, with times as ``utc_iso`` text and booleans as 0/1 or bool.
"""

from __future__ import annotations

import hashlib
import json
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, fields
from datetime import datetime
from typing import Any
from uuid import UUID

from station.core import Trims
from station.runs import (
    LimitCheck,
    RecipeRef,
    Ripple,
    Run,
    RunKind,
    Verdict,
    limit_name,
    parse_utc_iso,
    utc_iso,
)

Row = Mapping[str, Any]


@dataclass(frozen=True)
class RunFilter:
    """What QA asks for; every field left None matches everything.

    ``since`` and ``until`` bound ``started_at`` inclusively. With ``limit``,
    the newest ``limit`` matching runs are kept (a dashboard's "last 50"), still
    returned oldest first like every other list of runs.
    """

    serial: str | None = None
    since: datetime | None = None
    until: datetime | None = None
    recipe: str | None = None
    verdict: Verdict | None = None
    station_id: int | None = None
    limit: int | None = None

    def __post_init__(self) -> None:
        if self.limit is not None and self.limit < 0:
            raise ValueError(f"limit must be >= 0, got {self.limit}")


@dataclass(frozen=True)
class VerificationRecord:
    """A unit's drive trims read back and compared with what the station recorded.

    ``recorded_run_id`` and ``recorded_trims`` are None when the station has no
    stored trims for the unit at all, which is itself a finding.
    """

    serial: str
    verified_at: datetime
    station_id: int
    operator: str
    bench: str
    match: bool
    drive_trims: Trims
    recorded_run_id: int | None
    recorded_trims: Trims | None


# Column names are the dataclass's field names, so a new trim cannot be forgotten here.
TRIM_FIELDS = tuple(f.name for f in fields(Trims))
RIPPLE_FIELDS = tuple(f.name for f in fields(Ripple))

# What is known when a run begins: written once by begin_run, never updated.
START_COLUMNS = (
    "serial",
    "kind",
    "recipe_name",
    "recipe_version",
    "recipe_sha256",
    "station_id",
    "operator",
    "software_version",
    "bench",
    "started_at",
    "service_reason",
    "previous_run_id",
    "run_uuid",
)


def _group(prefix: str, names: Sequence[str]) -> tuple[str, ...]:
    return tuple(f"{prefix}_{name}" for name in names)


# What the run learns: finish_run writes all of these, once (a finished run is final).
_TRIM_GROUPS = ("trims_before", "trims_after", "trims_estimated", "uncertainty")
_RIPPLE_GROUPS = ("before", "after")
RESULT_COLUMNS = (
    "finished_at",
    "verdict",
    "reason",
    *(column for prefix in _TRIM_GROUPS for column in _group(prefix, TRIM_FIELDS)),
    "trims_stored",
    *(column for prefix in _RIPPLE_GROUPS for column in _group(prefix, RIPPLE_FIELDS)),
    "method",
    "fit",
    "warnings",
    "recording",
    "recording_sha256",
    "motion_s",
)
LIMIT_COLUMNS = ("run_id", "name", "position", "value", "low", "high", "unit", "passed", "note")
VERIFICATION_COLUMNS = (
    "serial",
    "verified_at",
    "station_id",
    "operator",
    "bench",
    "trims_match",
    *_group("drive", TRIM_FIELDS),
    "recorded_run_id",
    *_group("recorded", TRIM_FIELDS),
)


def _time_or_none(moment: datetime | None) -> str | None:
    return None if moment is None else utc_iso(moment)


def _parse_or_none(text: str | None) -> datetime | None:
    return None if text is None else parse_utc_iso(text)


def _group_values(
    prefix: str, names: Sequence[str], value: Trims | Ripple | None
) -> dict[str, float | None]:
    columns = _group(prefix, names)
    if value is None:
        return dict.fromkeys(columns)
    return {column: getattr(value, name) for column, name in zip(columns, names, strict=True)}


def trim_values(prefix: str, trims: Trims | None) -> dict[str, float | None]:
    return _group_values(prefix, TRIM_FIELDS, trims)


def _ripple_values(prefix: str, ripple: Ripple | None) -> dict[str, float | None]:
    return _group_values(prefix, RIPPLE_FIELDS, ripple)


def _floats_from(row: Row, columns: Sequence[str]) -> list[float] | None:
    """A group of REAL columns: None when all are NULL.

    SQLite stores NaN as NULL, so a NULL beside numbers was a NaN.
    """
    raw = [row[column] for column in columns]
    if all(value is None for value in raw):
        return None
    return [math.nan if value is None else float(value) for value in raw]


def trims_from(row: Row, prefix: str) -> Trims | None:
    values = _floats_from(row, _group(prefix, TRIM_FIELDS))
    return None if values is None else Trims(*values)


def required_trims(row: Row, prefix: str) -> Trims:
    trims = trims_from(row, prefix)
    if trims is None:  # the schema makes these columns NOT NULL
        raise ValueError(f"{prefix} trims missing from a row that requires them")
    return trims


def _ripple_from(row: Row, prefix: str) -> Ripple | None:
    values = _floats_from(row, _group(prefix, RIPPLE_FIELDS))
    return None if values is None else Ripple(*values)


def start_values(run: Run) -> dict[str, object]:
    return {
        "serial": run.serial,
        "kind": run.kind.value,
        "recipe_name": run.recipe.name,
        "recipe_version": run.recipe.version,
        "recipe_sha256": run.recipe.sha256,
        "station_id": run.station_id,
        "operator": run.operator,
        "software_version": run.software_version,
        "bench": run.bench,
        "started_at": utc_iso(run.started_at),
        "service_reason": run.service_reason,
        "previous_run_id": run.previous_run_id,
        "run_uuid": None if run.run_uuid is None else str(run.run_uuid),
    }


def result_values(run: Run) -> dict[str, object]:
    values: dict[str, object] = {
        "run_id": run.run_id,
        "finished_at": _time_or_none(run.finished_at),
        "verdict": None if run.verdict is None else run.verdict.value,
        "reason": run.reason,
        **trim_values("trims_before", run.trims_before),
        **trim_values("trims_after", run.trims_after),
        **trim_values("trims_estimated", run.trims_estimated),
        **trim_values("uncertainty", run.uncertainty),
        "trims_stored": int(run.trims_stored),
        **_ripple_values("before", run.before),
        **_ripple_values("after", run.after),
        "method": run.method,
        # JSON keeps the fit's nesting and the warnings' order without more tables.
        "fit": None if run.fit is None else json.dumps(run.fit),
        "warnings": json.dumps(run.warnings),
        "recording": run.recording,
        "recording_sha256": run.recording_sha256,
        "motion_s": run.motion_s,
    }
    return values


SELECT_RUNS = ("SELECT runs.*, recipes.text AS recipe_text FROM runs "
               "LEFT JOIN recipes ON recipes.sha256 = runs.recipe_sha256")
"""Runs with the text of their recipe: a record carries its own meaning."""


def run_from(row: Row, limits: Sequence[LimitCheck]) -> Run:
    """A run as its row (``SELECT_RUNS``) holds it; frozen when finished: a record is
    never changed."""
    run = Run(
        serial=row["serial"],
        kind=RunKind(row["kind"]),
        recipe=RecipeRef(row["recipe_name"], row["recipe_version"], row["recipe_sha256"],
                         row["recipe_text"]),
        station_id=row["station_id"],
        operator=row["operator"],
        software_version=row["software_version"],
        bench=row["bench"],
        started_at=parse_utc_iso(row["started_at"]),
        service_reason=row["service_reason"],
        previous_run_id=row["previous_run_id"],
        run_uuid=None if row["run_uuid"] is None else UUID(str(row["run_uuid"])),
        run_id=row["run_id"],
        finished_at=_parse_or_none(row["finished_at"]),
        verdict=None if row["verdict"] is None else Verdict(row["verdict"]),
        reason=row["reason"],
        limits=tuple(limits),
        trims_before=trims_from(row, "trims_before"),
        trims_after=trims_from(row, "trims_after"),
        trims_stored=bool(row["trims_stored"]),
        trims_estimated=trims_from(row, "trims_estimated"),
        uncertainty=trims_from(row, "uncertainty"),
        before=_ripple_from(row, "before"),
        after=_ripple_from(row, "after"),
        method=row["method"],
        fit=None if row["fit"] is None else json.loads(row["fit"]),
        warnings=json.loads(row["warnings"]),
        recording=row["recording"],
        recording_sha256=row["recording_sha256"],
        motion_s=row["motion_s"],
    )
    return run.freeze() if run.verdict is not None and run.finished_at is not None else run


def limit_values(run_id: int, position: int, check: LimitCheck) -> dict[str, object]:
    return {
        "run_id": run_id,
        "name": str(check.name),
        "position": position,
        "value": check.value,
        "low": check.low,
        "high": check.high,
        "unit": check.unit,
        "passed": None if check.passed is None else int(check.passed),  # NULL: did not apply
        "note": check.note,
    }


def limit_from(row: Row) -> LimitCheck:
    return LimitCheck(
        name=limit_name(row["name"]),
        value=row["value"],
        low=row["low"],
        high=row["high"],
        unit=row["unit"],
        passed=None if row["passed"] is None else bool(row["passed"]),
        note=row["note"],
    )


def verification_values(v: VerificationRecord) -> dict[str, object]:
    return {
        "serial": v.serial,
        "verified_at": utc_iso(v.verified_at),
        "station_id": v.station_id,
        "operator": v.operator,
        "bench": v.bench,
        "trims_match": int(v.match),
        **trim_values("drive", v.drive_trims),
        "recorded_run_id": v.recorded_run_id,
        **trim_values("recorded", v.recorded_trims),
    }


def verification_from(row: Row) -> VerificationRecord:
    return VerificationRecord(
        serial=row["serial"],
        verified_at=parse_utc_iso(row["verified_at"]),
        station_id=row["station_id"],
        operator=row["operator"],
        bench=row["bench"],
        match=bool(row["trims_match"]),
        drive_trims=required_trims(row, "drive"),
        recorded_run_id=row["recorded_run_id"],
        recorded_trims=trims_from(row, "recorded"),
    )


def recipe_values(run: Run, recipe_text: str) -> dict[str, object]:
    """The recipe row a run's beginning stores, once per text: the hash is how a run
    finds its recipe again, so a run whose hash is not its text's is refused."""
    digest = hashlib.sha256(recipe_text.encode("utf-8")).hexdigest()
    if digest != run.recipe.sha256:
        raise ValueError(
            f"recipe {run.recipe.name} {run.recipe.version}: sha256 {run.recipe.sha256} "
            f"is not the hash of the text given ({digest})"
        )
    return {"sha256": digest, "name": run.recipe.name, "version": run.recipe.version,
            "text": recipe_text, "first_used_at": utc_iso(run.started_at)}


def filter_clauses(f: RunFilter, mark: str) -> tuple[str, list[object]]:
    """The WHERE clause (or nothing) of a QA filter, with ``mark`` as the placeholder of
    the backend's driver (``?``, ``%s``), and its parameters: QA's question is asked of
    every database in the same words."""
    terms, params = filter_terms(f, mark)
    return (f"WHERE {' AND '.join(terms)}" if terms else ""), params


def filter_terms(f: RunFilter, mark: str) -> tuple[list[str], list[object]]:
    """The conditions of a QA filter on the runs table, to be joined with AND."""
    terms: list[str] = []
    params: list[object] = []
    for column, op, value in (
        ("serial", "=", f.serial),
        ("started_at", ">=", None if f.since is None else utc_iso(f.since)),
        ("started_at", "<=", None if f.until is None else utc_iso(f.until)),
        ("recipe_name", "=", f.recipe),
        ("verdict", "=", None if f.verdict is None else f.verdict.value),
        ("station_id", "=", f.station_id),
    ):
        if value is not None:
            terms.append(f"runs.{column} {op} {mark}")
            params.append(value)
    return terms, params


def check_finishable(run: Run) -> None:
    """Refuse (ValueError) a run no store may finish: never begun, without its verdict and
    finishing time (a run still going has nothing to finish), or judged twice on a limit."""
    if run.run_id is None:
        raise ValueError(f"run of {run.serial} was never begun")
    if run.verdict is None or run.finished_at is None:
        raise ValueError(
            f"run {run.run_id}: a run is finished with its verdict and finishing time"
        )
    names = [check.name for check in run.limits]
    if len(set(names)) != len(names):
        raise ValueError(f"run {run.run_id}: a limit is checked twice in {names}")
