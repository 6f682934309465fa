"""QA's statistics aggregated by the database, in the same words for every backend.

``station stats`` over a line's year is a million runs; fetching them to count them
would take minutes and the memory of a million dataclasses. The database sums instead:
per recipe, verdict and whether trims were stored, the count and the sums of each
quantity less a pivot (``qa.Moments``), three statements whatever the number of runs.
Capability is judged against the bounds the runs' own limit checks carried (the newest
run's, where the software that judged a recipe changed), never a recipe re-parsed.

A store hands ``recipe_statistics`` a function that runs one statement inside its read
transaction, so every figure comes from one snapshot while other stations write.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

from station.qa import Moments, RecipeStatistics
from station.rows import Row, RunFilter, filter_terms
from station.runs import LimitName, RecipeRef, Verdict

Execute = Callable[[str, Sequence[object]], Sequence[Row]]
"""Run one statement of the store's dialect in its read transaction; return its rows."""


@dataclass(frozen=True)
class Quantity:
    """One quantity QA follows: its column, and the limit check it is judged against."""

    key: str
    column: str
    limit: LimitName
    stored_trims_only: bool  # trims count only where the run stored them in the drive


QUANTITIES = (
    Quantity("offset_a_mA", "trims_after_offset_a_mA", LimitName.OFFSET_A, True),
    Quantity("offset_b_mA", "trims_after_offset_b_mA", LimitName.OFFSET_B, True),
    Quantity("gain_a", "trims_after_gain_a", LimitName.GAIN_A, True),
    Quantity("gain_b", "trims_after_gain_b", LimitName.GAIN_B, True),
    Quantity("h1_after_mps2", "after_h1", LimitName.H1_AFTER, False),
    Quantity("h2_after_mps2", "after_h2", LimitName.H2_AFTER, False),
)

_NEWEST_RUNS = 1000
"""How many of a recipe's newest runs are searched for its bounds before its checks are."""

_BOUNDED = "(limit_checks.low IS NOT NULL OR limit_checks.high IS NOT NULL)"
"""A limit check that carried bounds (one that did not apply carries none)."""

MEASURED = frozenset({Verdict.PASS, Verdict.FAIL})
"""Runs that measured a unit; an error or an abort measured nothing."""


@dataclass
class _Group:
    runs: int = 0
    verdicts: dict[Verdict, int] = field(default_factory=lambda: dict.fromkeys(Verdict, 0))
    moments: list[Moments] = field(default_factory=list)


def recipe_statistics(execute: Execute, f: RunFilter, mark: str) -> list[RecipeStatistics]:
    """Counts, verdicts and capability per recipe version of the runs ``f`` selects,
    ``mark`` being the driver's placeholder (``?``, ``%s``)."""
    terms, params = filter_terms(f, mark)
    pivots = _pivots(execute, terms, params)
    groups: dict[str, _Group] = {}
    for row in execute(*_moments_statement(terms, params, pivots, mark)):
        group = groups.setdefault(row["sha"], _Group(moments=[Moments(p) for p in pivots]))
        group.runs += int(row["runs"])
        verdict = None if row["verdict"] is None else Verdict(row["verdict"])
        if verdict is not None:
            group.verdicts[verdict] += int(row["runs"])
        if verdict not in MEASURED:
            continue
        for i, quantity in enumerate(QUANTITIES):
            if quantity.stored_trims_only and not row["stored"]:
                continue
            n = int(row["trims" if quantity.stored_trims_only else "ripple"])
            group.moments[i] += Moments(pivots[i], n, float(row[f"s{i}"] or 0.0),
                                        float(row[f"q{i}"] or 0.0))
    refs = _recipes(execute, sorted(groups), mark)
    out = []
    for sha, group in groups.items():
        bounds = _bounds(execute, terms, params, sha=sha, selected=group.runs, mark=mark)
        quantities = {quantity.key: moments.capability(*bounds[quantity.limit])
                      for moments, quantity in zip(group.moments, QUANTITIES, strict=True)}
        out.append(RecipeStatistics(refs[sha], group.runs, group.verdicts, quantities))
    out.sort(key=lambda s: (s.recipe.name, s.recipe.version))
    return out


def _where(terms: Sequence[str]) -> str:
    return f"WHERE {' AND '.join(terms)}" if terms else ""


def _pivots(execute: Execute, terms: list[str], params: list[object]) -> list[float]:
    """One value of each quantity among the selected runs (0 where there is none)."""
    columns = []
    all_params: list[object] = []
    for i, quantity in enumerate(QUANTITIES):
        where = _where([*terms, f"runs.{quantity.column} IS NOT NULL"])
        columns.append(f"COALESCE((SELECT runs.{quantity.column} FROM runs {where} LIMIT 1), 0)"
                       f" AS p{i}")
        all_params.extend(params)
    (row,) = execute(f"SELECT {', '.join(columns)}", all_params)
    return [float(row[f"p{i}"]) for i in range(len(QUANTITIES))]


def _moments_statement(terms: list[str], params: list[object], pivots: list[float],
                       mark: str) -> tuple[str, list[object]]:
    """Counts and sums by recipe, verdict and stored trims. A run's trims (and its ripple
    after) are recorded all together or not at all, so one count serves each group of
    columns: every aggregate step costs time over a million rows."""
    sums = [f"COUNT(runs.{QUANTITIES[0].column}) AS trims",
            f"COUNT(runs.{QUANTITIES[-1].column}) AS ripple"]
    sum_params: list[object] = []
    for i, (quantity, pivot) in enumerate(zip(QUANTITIES, pivots, strict=True)):
        column = f"runs.{quantity.column}"
        shifted = f"({column} - {mark})"
        sums.append(f"SUM{shifted} AS s{i}, SUM({shifted} * {shifted}) AS q{i}")
        sum_params.extend((pivot, pivot, pivot))
    sql = (f"SELECT runs.recipe_sha256 AS sha, runs.verdict AS verdict, "
           f"runs.trims_stored AS stored, COUNT(*) AS runs, {', '.join(sums)} FROM runs "
           f"{_where(terms)} GROUP BY runs.recipe_sha256, runs.verdict, runs.trims_stored")
    return sql, [*sum_params, *params]


def _recipes(execute: Execute, shas: list[str], mark: str) -> dict[str, RecipeRef]:
    if not shas:
        return {}
    rows = execute(f"SELECT sha256, name, version FROM recipes WHERE sha256 IN "
                   f"({', '.join([mark] * len(shas))})", shas)
    return {row["sha256"]: RecipeRef(row["name"], row["version"], row["sha256"]) for row in rows}


Bounds = tuple[float | None, float | None]


def _bounds(execute: Execute, terms: list[str], params: list[object], *, sha: str,
            selected: int, mark: str) -> dict[LimitName, Bounds]:
    """For each quantity's limit, the bounds of the newest selected run of the recipe
    that checked it with any; none where no run did (capability is then mean and spread
    only). A small selection is read whole, in one statement, by whatever index its
    filter has (a serial's dozen runs); a large one is searched per limit."""
    names = [quantity.limit for quantity in QUANTITIES]
    if selected > _NEWEST_RUNS:
        return {name: _newest_bounds(execute, terms, params, sha=sha, name=name, mark=mark)
                for name in names}
    where = _where([*terms, f"runs.recipe_sha256 = {mark}", _BOUNDED,
                    f"limit_checks.name IN ({', '.join([mark] * len(names))})"])
    rows = execute(f"SELECT limit_checks.name AS name, limit_checks.low AS low, "
                   f"limit_checks.high AS high, runs.started_at AS started_at FROM runs "
                   f"JOIN limit_checks ON limit_checks.run_id = runs.run_id {where}",
                   [*params, sha, *(name.value for name in names)])
    newest: dict[LimitName, tuple[Any, Bounds]] = {}
    for row in rows:
        name = LimitName(row["name"])
        # Text in SQLite, a datetime in PostgreSQL: each sorts within its own kind.
        if name not in newest or row["started_at"] > newest[name][0]:
            newest[name] = (row["started_at"], _floats(row))
    return {name: newest[name][1] if name in newest else (None, None) for name in names}


def _newest_bounds(execute: Execute, terms: list[str], params: list[object], *, sha: str,
                   name: LimitName, mark: str) -> Bounds:
    """Nearly always the recipe's newest run has the check, so its newest runs are read
    first; a check that is rare or absent among them is looked for from the checks' side
    instead, so that neither case walks a million runs."""
    newest = (f"SELECT runs.run_id, runs.started_at FROM runs "
              f"{_where([*terms, f'runs.recipe_sha256 = {mark}'])} "
              f"ORDER BY runs.started_at DESC LIMIT {_NEWEST_RUNS}")
    rows = execute(f"SELECT limit_checks.low AS low, limit_checks.high AS high "
                   f"FROM ({newest}) AS recent JOIN limit_checks "
                   f"ON limit_checks.run_id = recent.run_id AND limit_checks.name = {mark} "
                   f"WHERE {_BOUNDED} ORDER BY recent.started_at DESC LIMIT 1",
                   [*params, sha, name.value])
    if not rows:
        # CROSS JOIN keeps SQLite's loop on the checks (PostgreSQL plans it by its stats).
        where = _where([f"limit_checks.name = {mark}", _BOUNDED,
                        "runs.run_id = limit_checks.run_id", *terms,
                        f"runs.recipe_sha256 = {mark}"])
        rows = execute(f"SELECT limit_checks.low AS low, limit_checks.high AS high "
                       f"FROM limit_checks CROSS JOIN runs {where} "
                       f"ORDER BY runs.started_at DESC LIMIT 1", [name.value, *params, sha])
    return _floats(rows[0]) if rows else (None, None)


def _floats(row: Row) -> Bounds:
    low, high = row["low"], row["high"]
    return (None if low is None else float(low)), (None if high is None else float(high))
