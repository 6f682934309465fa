"""QA's commands on a database of known runs: statistics, history as people read it, recipes.

The runs are written with the store directly (no bench), so the expected
means, deviations and Cpk can be computed by hand.
"""

from __future__ import annotations

import csv
import hashlib
import io
import json
import math
import statistics
import sys
from dataclasses import replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any
from uuid import uuid4

import pytest

from station.cli import main
from station.core import Trims
from station.limits import bound_checks, ripple_checks, summary, verdict_for
from station.recipes import Recipe, RecipeError, load_recipe, parse_recipe
from station.records import statistics as recipe_statistics
from station.rows import RunFilter
from station.runs import LimitCheck, RecipeRef, Ripple, Run, RunKind, Verdict
from station.store import Store
from tests.cli import run_cli

OFFSETS_A = (60.0, 64.0, 68.0, 72.0)
H1_AFTER = (0.004, 0.006, 0.005, 0.007)
H1_LIMIT = 0.0065
"""The line's recipe: the default with a tighter H1 limit, which SN503 fails."""


def _line_recipe() -> Recipe:
    text = load_recipe("default").text.replace("max_h1_after_mps2 = 0.08",
                                               f"max_h1_after_mps2 = {H1_LIMIT}")
    return parse_recipe(text, source="line")


def _run(serial: str, recipe: Recipe, offset_a: float, h1: float, started: datetime,
         ref: RecipeRef | None = None) -> Run:
    """A run as the procedure records it: every limit check with its bounds."""
    run = Run(
        serial=serial, kind=RunKind.CALIBRATE,
        recipe=ref or RecipeRef(recipe.name, recipe.version, recipe.sha256), station_id=3,
        operator="qa", software_version="test", bench="sim", started_at=started,
    )
    run.finished_at = started + timedelta(seconds=20)
    run.trims_before = Trims()
    run.trims_after = Trims(offset_a, -20.0, 9950.0, 10050.0)
    run.trims_stored = True
    run.before = Ripple(1.2, 0.5)
    run.after = Ripple(h1, 0.01)
    run.limits = (*bound_checks(recipe.limits, run.trims_after),
                  *ripple_checks(recipe.limits, run.before, run.after))
    run.verdict = verdict_for(run.limits)
    run.reason = summary(run.limits)
    return run


def _store_line(path: Path, recipe: Recipe, text: str, ref: RecipeRef | None = None) -> None:
    start = datetime(2026, 3, 1, 8, 0, tzinfo=UTC)
    with Store(path) as store:
        for i, (offset, h1) in enumerate(zip(OFFSETS_A, H1_AFTER, strict=True)):
            run = _run(f"SN{500 + i}", recipe, offset, h1, start + timedelta(hours=i), ref)
            store.begin_run(run, text)
            store.finish_run(run)
        errored = _run("SN599", recipe, 0.0, 0.0, start + timedelta(days=1), ref)
        errored.trims_after, errored.after, errored.trims_stored = None, None, False
        errored.limits, errored.verdict, errored.reason = (), Verdict.ERROR, "sensor: silent"
        store.begin_run(errored, text)
        store.finish_run(errored)


@pytest.fixture
def db(tmp_path: Path) -> Path:
    path = tmp_path / "qa.db"
    recipe = _line_recipe()
    _store_line(path, recipe, recipe.text)
    return path


def _cli(args: list[str], monkeypatch: pytest.MonkeyPatch,
         capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    outcome = run_cli(args, monkeypatch, capsys)
    return outcome.code, outcome.stdout


def test_statistics_give_mean_std_and_cpk_against_the_recipes_limits(db: Path) -> None:
    (stats,) = recipe_statistics(db, RunFilter())
    limits = _line_recipe().limits
    assert stats.runs == 5
    assert stats.verdicts[Verdict.PASS] == 3 and stats.verdicts[Verdict.FAIL] == 1
    assert stats.verdicts[Verdict.ERROR] == 1
    offset = stats.quantities["offset_a_mA"]
    mean, std = statistics.mean(OFFSETS_A), statistics.stdev(OFFSETS_A)
    assert offset.n == 4  # the error measured nothing and does not count
    assert offset.mean == pytest.approx(mean) and offset.std == pytest.approx(std)
    bound = limits.offset_bound_mA
    assert offset.cpk == pytest.approx(min(bound - mean, mean + bound) / (3 * std))
    h1 = stats.quantities["h1_after_mps2"]
    h1_mean, h1_std = statistics.mean(H1_AFTER), statistics.stdev(H1_AFTER)
    assert h1.low is None and h1.high == limits.max_h1_after_mps2
    assert h1.cpk == pytest.approx((limits.max_h1_after_mps2 - h1_mean) / (3 * h1_std))


def test_statistics_follow_the_filters(db: Path) -> None:
    (stats,) = recipe_statistics(
        db, RunFilter(until=datetime(2026, 3, 1, 9, 30, tzinfo=UTC))
    )
    assert stats.runs == 2
    assert recipe_statistics(db, RunFilter(recipe="paper")) == []


def test_stats_command_prints_json_per_recipe_version(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["stats", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0
    (doc,) = json.loads(out)
    assert doc["recipe"] == "default" and doc["recipe_sha256"] == _line_recipe().sha256
    assert doc["verdicts"] == {"pass": 3, "fail": 1, "error": 1, "aborted": 0}
    offset: dict[str, Any] = doc["quantities"]["offset_a_mA"]
    assert offset["n"] == 4 and math.isclose(offset["mean"], statistics.mean(OFFSETS_A))
    # Four values give a Cpk, with its standard error and a caution beside it.
    assert offset["cpk"] is not None and offset["cpk_rough"] is True
    assert math.isclose(offset["cpk_sigma"],
                        math.sqrt(1 / 36 + offset["cpk"] ** 2 / 6), rel_tol=1e-12)
    code, out = _cli(["stats", "--db", str(db)], monkeypatch, capsys)
    assert "Cpk" in out and "offset_a_mA" in out
    assert f"{offset['cpk']:.2f} ± {offset['cpk_sigma']:.2f} *" in out
    assert "* Cpk from fewer than 30 runs: a rough guide" in " ".join(out.split())


def test_history_table_shows_each_run_for_people(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("COLUMNS", "80")
    code, out = _cli(["history", "SN503", "--db", str(db)], monkeypatch, capsys)
    assert code == 0
    assert "fail" in out and "h1_after_" in out and "+72/-20" in out
    assert max(len(line) for line in out.splitlines()) <= 80


def test_query_limit_keeps_the_newest_runs_oldest_first(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["query", "--limit", "2", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0
    assert [r["serial"] for r in json.loads(out)] == ["SN503", "SN599"]


def test_an_unparseable_date_is_a_usage_error(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["query", "--since", "last tuesday", "--db", str(db)], monkeypatch, capsys)
    assert code == 2 and out == ""


def test_recipes_command_lists_the_shipped_recipes(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["recipes", "--json"], monkeypatch, capsys)
    assert code == 0
    by_name = {d["name"]: d for d in json.loads(out)}
    assert set(by_name) >= {"default", "paper"}
    assert by_name["paper"]["method"] == "paper" and by_name["default"]["method"] == "coherent"


def test_an_error_run_shows_the_operator_an_error_banner_with_its_reason(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    bench = tmp_path / "unplugged.toml"
    bench.write_text('[sim]\n[[sim.faults]]\nkind = "sensor_unplugged"\nat_s = 1.0\n',
                     encoding="utf-8")
    monkeypatch.setenv("COLUMNS", "100")
    code, out = _cli(["calibrate", "SN123", "--bench", str(bench), "--db",
                      str(tmp_path / "s.db")], monkeypatch, capsys)
    assert code == 3
    assert "SN123: ERROR" in out and "not gravity" in " ".join(out.split())


def test_a_stored_run_with_an_unknown_limit_name_still_reads_back(db: Path) -> None:
    """A newer station may have written limits this version does not know."""
    with Store(db) as store:
        run = store.history("SN503")[0]
        future = replace(run, run_id=None, run_uuid=uuid4(), limits=(
            LimitCheck("thermal_drift_mA", 1.0, None, 2.0, "mA", True),
        ))
        store.begin_run(future, _line_recipe().text)
        store.finish_run(future)
        again = store.history("SN503")[-1]
    assert again.limits[0].name == "thermal_drift_mA"


def test_runs_of_a_recipe_this_version_no_longer_reads_keep_every_qa_command_working(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Records outlive software: runs stored under an older recipe format, one of whose
    keys has since been renamed. Statistics come from the records' own limit checks."""
    old = (_line_recipe().text.replace('format = "station-recipe/1"', 'format = "station-recipe/0"')
           .replace('name = "default"', 'name = "line-2025"')
           .replace("max_h1_after_mps2 =", "max_h1_after ="))
    with pytest.raises(RecipeError):
        parse_recipe(old)
    ref = RecipeRef("line-2025", "3", hashlib.sha256(old.encode("utf-8")).hexdigest())
    db = tmp_path / "old.db"
    _store_line(db, _line_recipe(), old, ref)

    (stats,) = recipe_statistics(db, RunFilter())
    assert stats.recipe == ref and stats.runs == 5
    h1 = stats.quantities["h1_after_mps2"]
    assert h1.high == H1_LIMIT and h1.cpk is not None
    assert stats.quantities["offset_a_mA"].high == _line_recipe().limits.offset_bound_mA
    for args in (["stats"], ["stats", "--json"], ["history", "SN503"], ["query", "--json"]):
        code, out = _cli([*args, "--db", str(db)], monkeypatch, capsys)
        assert code == 0 and out, args
    # Recalibrating with that recipe is refused in words, with what to do instead; naming
    # a recipe of today calibrates the unit, its previous record found.
    code, out = _cli(["recalibrate", "SN503", "--reason", "field return", "--db", str(db)],
                     monkeypatch, capsys)
    assert code == 2 and out == ""
    with Store(db) as store:
        assert len(store.history("SN503")) == 1
    code, out = _cli(["recalibrate", "SN503", "--reason", "field return", "--recipe",
                      "default", "--db", str(db), "--json"], monkeypatch, capsys)
    doc = json.loads(out)
    assert code == 0, doc["reason"]
    assert doc["previous_trims"]["offset_a_mA"] == OFFSETS_A[3]


def test_stats_gives_csv_one_row_per_recipe_version_and_quantity(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["stats", "--db", str(db), "--format", "csv"], monkeypatch, capsys)
    assert code == 0
    header, *rows = list(csv.reader(io.StringIO(out)))
    assert header[:5] == ["recipe", "recipe_version", "recipe_sha256", "runs", "quantity"]
    assert [r[4] for r in rows] == ["offset_a_mA", "offset_b_mA", "gain_a", "gain_b",
                                    "h1_after_mps2", "h2_after_mps2"]
    offset = dict(zip(header, rows[0], strict=True))
    assert int(offset["n"]) == 4 and float(offset["mean"]) == pytest.approx(
        statistics.mean(OFFSETS_A))
    code, out = _cli(["stats", "--db", str(db), "--format", "json"], monkeypatch, capsys)
    assert code == 0 and json.loads(out)[0]["runs"] == 5


@pytest.mark.parametrize("command", [["stats"], ["query"], ["history", "SN503"]])
def test_json_together_with_another_format_is_refused(
    db: Path, command: list[str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    monkeypatch.setattr(sys, "argv", ["station", *command, "--db", str(db), "--json",
                                      "--format", "csv"])
    with pytest.raises(SystemExit) as stop:
        main()
    captured = capsys.readouterr()
    assert stop.value.code == 2 and captured.out == ""
    assert "--json is --format json" in " ".join(captured.err.split())


def test_history_of_a_serial_without_runs_says_so(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, out = _cli(["history", "SN999", "--db", str(db)], monkeypatch, capsys)
    assert code == 0 and f"no runs of SN999 are recorded in {db}" in " ".join(out.split())
    code, out = _cli(["history", "SN999", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0 and json.loads(out) == []


@pytest.mark.parametrize("command", [["history"], ["stats"], ["calibrate"], ["sync"]])
def test_flags_show_no_value_type_in_help(
    command: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("COLUMNS", "200")
    code, out = _cli([*command, "--help"], monkeypatch, capsys)
    assert code == 0 and "--json" in out
    json_line = next(line for line in out.splitlines() if "--json" in line)
    assert "<bool>" not in json_line and "<int>" not in json_line
