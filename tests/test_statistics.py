"""QA's statistics summed by the database agree with the same figures computed one run at
a time in Python, on both backends, and keep their digits where the spread is small
against the mean."""

from __future__ import annotations

import math
import random
import statistics
from collections.abc import Iterator
from datetime import timedelta
from pathlib import Path

import pytest

from station.core import Trims
from station.pgstore import PostgresStore
from station.qa import Moments, RecipeStatistics, capability
from station.rows import RunFilter
from station.runs import LimitCheck, LimitName, Ripple, Run, Verdict
from station.statsql import MEASURED, QUANTITIES
from station.storage import RunStore
from station.store import Store
from tests.test_store import HERE, T0, _begin, _process_table, _record, _run


@pytest.fixture(params=["sqlite", "postgresql"])
def store(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[RunStore]:
    if request.param == "sqlite":
        with Store(tmp_path / "station.db", owner=HERE, probe=_process_table) as lite:
            yield lite
        return
    url = request.getfixturevalue("postgresql_url")
    with PostgresStore(url, owner=HERE, probe=_process_table) as pg:
        yield pg


def _line(store: RunStore, seed: int, runs: int = 120) -> None:
    """Runs as a line records them: two recipes, every verdict, trims stored or not,
    gains near 10000 that differ by little, and limits that changed half-way."""
    rng = random.Random(seed)
    for i in range(runs):
        run = _run(f"SN{100 + i % 17}", started_at=T0 + timedelta(minutes=i),
                   station_id=1 + i % 3, recipe=rng.choice(["default", "paper"]))
        verdict = rng.choices(list(Verdict), weights=[6, 2, 1, 1])[0]
        if verdict in MEASURED:
            high = 250.0 if i < runs // 2 else 200.0
            run.limits = (
                LimitCheck(LimitName.OFFSET_A, 0.0, -high, high, "mA", True),
                LimitCheck(LimitName.GAIN_A, 0.0, 9500.0, 10500.0, "units", True),
                LimitCheck(LimitName.H1_AFTER, 0.0, None, 0.05 + (i >= runs // 2) * 0.03,
                           "m/s²", True),
            )
            run.trims_after = Trims(rng.gauss(40, 30), rng.gauss(-20, 25),
                                    10000 + rng.gauss(0, 1e-3), 10000 + rng.gauss(3, 2))
            run.after = Ripple(abs(rng.gauss(0.02, 0.01)), abs(rng.gauss(0.01, 0.004)))
        _record(store, run, verdict, stored=verdict is Verdict.PASS and rng.random() < 0.9)
    _begin(store, _run("SN999", started_at=T0 + timedelta(days=1)))  # still running


def _expected(runs: list[Run]) -> list[RecipeStatistics]:
    """The statistics one run at a time: what `station stats` computed before the sums."""
    out = []
    for sha in {run.recipe.sha256 for run in runs}:
        members = [run for run in runs if run.recipe.sha256 == sha]
        measured = [r for r in members if r.verdict in MEASURED]
        trims = [r.trims_after for r in measured if r.trims_after is not None and r.trims_stored]
        after = [r.after for r in measured if r.after is not None]
        values = {
            "offset_a_mA": [t.offset_a_mA for t in trims],
            "offset_b_mA": [t.offset_b_mA for t in trims],
            "gain_a": [t.gain_a for t in trims], "gain_b": [t.gain_b for t in trims],
            "h1_after_mps2": [a.h1 for a in after], "h2_after_mps2": [a.h2 for a in after],
        }
        quantities = {}
        for quantity in QUANTITIES:
            low = high = None
            for run in sorted(members, key=lambda r: r.started_at, reverse=True):
                bounded = [c for c in run.limits if c.name == quantity.limit
                           and (c.low is not None or c.high is not None)]
                if bounded:
                    low, high = bounded[0].low, bounded[0].high
                    break
            quantities[quantity.key] = capability(values[quantity.key], low, high)
        verdicts = {v: sum(1 for r in members if r.verdict is v) for v in Verdict}
        out.append(RecipeStatistics(members[0].recipe, len(members), verdicts, quantities))
    return sorted(out, key=lambda s: (s.recipe.name, s.recipe.version))


def _assert_close(got: list[RecipeStatistics], want: list[RecipeStatistics]) -> None:
    assert [(s.recipe, s.runs, s.verdicts) for s in got] == \
        [(s.recipe, s.runs, s.verdicts) for s in want]
    for g, w in zip(got, want, strict=True):
        assert g.quantities.keys() == w.quantities.keys()
        for key, a in g.quantities.items():
            b = w.quantities[key]
            assert (a.n, a.low, a.high) == (b.n, b.low, b.high), key
            for x, y in ((a.mean, b.mean), (a.std, b.std), (a.cpk, b.cpk)):
                if y is None or math.isnan(y):
                    assert x is None or math.isnan(x), key
                else:
                    assert x == pytest.approx(y, rel=1e-9, abs=1e-12), key


@pytest.mark.parametrize("seed", [1, 2])
def test_statistics_summed_by_the_database_equal_those_of_each_run(
    store: RunStore, seed: int
) -> None:
    _line(store, seed)
    everything = store.query(RunFilter())
    got = store.statistics(RunFilter())
    assert len(got) == 2 and sum(s.runs for s in got) == len(everything)
    _assert_close(got, _expected(everything))
    # The gains' spread (1e-3 about 10000) survives the sums.
    gain = got[0].quantities["gain_a"]
    assert 5e-4 < gain.std < 2e-3
    # Limits that changed half-way: the newest run's bounds judge the recipe.
    assert {s.quantities["offset_a_mA"].high for s in got} == {200.0}


def test_statistics_of_a_selection_are_those_of_its_runs(store: RunStore) -> None:
    _line(store, 3)
    for selection in (RunFilter(station_id=2), RunFilter(until=T0 + timedelta(minutes=59)),
                      RunFilter(recipe="paper", verdict=Verdict.PASS), RunFilter(serial="SN105")):
        _assert_close(store.statistics(selection), _expected(store.query(selection)))
    early = store.statistics(RunFilter(until=T0 + timedelta(minutes=59)))
    assert {s.quantities["h1_after_mps2"].high for s in early} == {0.05}
    assert store.statistics(RunFilter(serial="SN-none")) == []


def test_a_recipe_without_a_check_has_spread_but_no_cpk(store: RunStore) -> None:
    run = _run("SN1")
    run.trims_after = Trims(1.0, 2.0, 10000.0, 10000.0)
    _record(store, run)
    second = _run("SN2", started_at=T0 + timedelta(minutes=1))
    second.trims_after = Trims(3.0, 2.0, 10000.0, 10002.0)
    _record(store, second)
    (stats,) = store.statistics(RunFilter())
    offset = stats.quantities["offset_a_mA"]
    assert (offset.n, offset.mean, offset.low, offset.high, offset.cpk) == (2, 2.0, None, None,
                                                                           None)
    assert offset.std == pytest.approx(math.sqrt(2.0))
    h1 = stats.quantities["h1_after_mps2"]  # no run measured the ripple after
    assert (h1.n, h1.cpk) == (0, None) and math.isnan(h1.mean) and math.isnan(h1.std)


def test_moments_about_a_pivot_keep_a_small_spread_of_large_values() -> None:
    rng = random.Random(7)
    values = [1e4 + rng.gauss(0, 1e-4) for _ in range(10_000)]
    pivot = values[0]
    moments = Moments(pivot)
    for half in (values[:5000], values[5000:]):  # summed apart, as groups are
        shifted = [v - pivot for v in half]
        moments += Moments(pivot, len(half), math.fsum(shifted), math.fsum(s * s for s in shifted))
    got = moments.capability(1e4 - 1e-3, 1e4 + 1e-3)
    assert got.std == pytest.approx(statistics.stdev(values), rel=1e-6)
    assert got.mean == pytest.approx(statistics.fmean(values), rel=1e-15)
    assert got.cpk == pytest.approx(capability(values, 1e4 - 1e-3, 1e4 + 1e-3).cpk, rel=1e-6)
    with pytest.raises(ValueError, match="same pivot"):
        moments + Moments(pivot + 1.0)
    with pytest.raises(ValueError, match="above high limit"):
        moments.capability(2.0, 1.0)
