"""Calibration methods are plug-ins: each names its recipe table and what it needs of the
bench, and plans its holds given what was measured; a new one is one module, registered
by name, with nothing changed in the recipes' reader or the procedure."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

import pytest

from station import methods
from station.core import Method
from station.methods import SWEEPS, Batch, Plan, SweepContext, for_run, sweep_method
from station.methods.magnitude import METHOD as MAGNITUDE
from station.methods.magnitude import MagnitudeSweep
from station.recipes import RecipeError, load_recipe, parse_recipe
from station.tomltable import TomlTable
from tests.test_calibrate import _recipe_variant
from tests.test_calibrate import _run as _cli


def test_every_registered_method_is_found_by_its_name() -> None:
    for name in SWEEPS:
        method = sweep_method(name)
        assert method.name == name
        assert method.estimates in Method
    assert sweep_method("coherent").needs_angle and not sweep_method("paper").needs_angle
    with pytest.raises(ValueError, match=r"no calibration method .bayes. .*paper, coherent"):
        sweep_method("bayes")


def test_a_drive_without_its_angle_gets_the_recipe_s_angle_free_method() -> None:
    recipe = load_recipe("default")
    chosen, settings = for_run(recipe, sees_angle=True)
    assert (chosen.name, settings) == ("coherent", recipe.sweep)
    chosen, settings = for_run(recipe, sees_angle=False)
    assert (chosen.name, settings) == ("magnitude", recipe.magnitude_sweep)
    assert isinstance(settings, MagnitudeSweep)
    chosen, _ = for_run(load_recipe("paper"), sees_angle=False)
    assert chosen.name == "paper"


def test_a_recipe_naming_no_registered_method_is_refused_with_the_known_ones() -> None:
    text = load_recipe("default").text.replace('method = "coherent"', 'method = "bayes"')
    with pytest.raises(RecipeError, match="method: must be one of 'paper', 'coherent'"):
        parse_recipe(text)


# -- a method added as one module ------------------------------------------------------


@dataclass(frozen=True)
class Narrowing:
    offset_spans_mA: tuple[int, ...]


class NarrowingMethod:
    """A method that is not among the shipped ones: the paper's parabolas in rounds of
    its own spans, with gain spans ten times the offsets'."""

    name = "narrowing"
    settings_type = Narrowing
    table = "narrowing_sweep"
    needs_angle = False
    estimates = Method.PAPER

    def __init__(self) -> None:
        self.batches: list[Batch] = []

    def read(self, t: TomlTable, rated_mA: int | None) -> Narrowing:
        spans = t.int_array("offset_spans_mA")
        t.finish()
        return Narrowing(spans)

    def plan(self, settings: Any, ctx: SweepContext) -> Plan:
        spans = settings.offset_spans_mA
        inner = MAGNITUDE.plan(MagnitudeSweep(spans, tuple(10 * s for s in spans), 4, 2, 5), ctx)
        batch = next(inner)
        try:
            while True:
                self.batches.append(batch)
                batch = inner.send((yield batch))
        except StopIteration as done:
            return done.value  # type: ignore[no-any-return]


METHOD: Final = NarrowingMethod()


def test_a_method_added_as_one_module_reads_its_table_and_calibrates_a_unit(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setitem(methods.SWEEPS, "narrowing", __name__)
    METHOD.batches.clear()
    path = _recipe_variant(tmp_path, "narrow", without="sweep")
    text = path.read_text(encoding="utf-8").replace('method = "coherent"',
                                                    'method = "narrowing"')
    path.write_text(f"{text}\n[narrowing_sweep]\noffset_spans_mA = [300, 80, 25]\n",
                    encoding="utf-8")
    recipe = load_recipe(path)
    assert recipe.sweep == Narrowing((300, 80, 25)) and recipe.angle_free
    # Its table is checked as strictly as the shipped ones'.
    typo = path.read_text(encoding="utf-8").replace("offset_spans_mA =", "offset_span_mA =")
    with pytest.raises(RecipeError, match=r"narrowing_sweep\.offset_span_mA"):
        parse_recipe(typo)
    # A [sweep] table it does not read is a problem, not silently ignored.
    with pytest.raises(RecipeError, match="sweep"):
        parse_recipe(f"{path.read_text(encoding='utf-8')}\n[sweep]\noffset_steps_mA = [100]\n")

    db = tmp_path / "station.db"
    code, doc = _cli(["calibrate", "SN123", "--recipe", str(path), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 0, doc["reason"]
    assert doc["verdict"] == "pass" and doc["method"] == "paper"
    assert len(METHOD.batches) == 9  # three rounds of three axes, each held as planned
    assert re.match(r"round 3/3: gain_split ±250 around", METHOD.batches[-1].label)
