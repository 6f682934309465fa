"""Each id of the vocabulary is one module of ``station.diagnosis.effects``, found by id."""

from __future__ import annotations

import ast
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from station.core import Effect
from station.diagnosis import effects
from station.diagnosis.effects import (
    DEFAULT_EXPERIMENT,
    MODULES,
    EffectTerms,
    UnknownEffectError,
    every,
    separating_experiment,
    terms,
)
from station.diagnosis.layout import ChainKind, ModelSpec
from station.diagnosis.model import layout_for


@pytest.fixture
def fresh_registry() -> Iterator[None]:
    """The registry's cache emptied before and after: a test may point an id elsewhere."""
    terms.cache_clear()
    yield
    terms.cache_clear()


def _obs(gear_ratio: float) -> Any:
    """What the layout reads of a recording."""
    meta = SimpleNamespace(rated_current_mA=1500, gear_ratio=gear_ratio, sync_period_s=1e-3)
    return SimpleNamespace(metadata=meta, conditions=[None] * 6, axis_mixed=False)


def test_every_id_is_declared_by_the_module_named_after_it() -> None:
    assert set(MODULES) == set(Effect)
    for effect in Effect:
        declared = terms(effect)
        assert isinstance(declared, EffectTerms)
        assert declared.effect is effect
        assert MODULES[effect] == effect.value
    assert [t.effect for t in every()] == list(Effect)


def test_an_id_is_imported_only_when_it_is_first_asked_for() -> None:
    probe = (
        "import sys\n"
        "from station.diagnosis import effects\n"
        "from station.core import Effect\n"
        "loaded = lambda: {m for m in sys.modules if m.startswith('station.diagnosis.effects.')}\n"
        "assert not loaded() - {'station.diagnosis.effects.readings'}, loaded()\n"
        "effects.terms(Effect.DETENT_TORQUE)\n"
        "assert 'station.diagnosis.effects.detent_torque' in loaded()\n"
        "assert 'station.diagnosis.effects.sensor_clock_drift' not in loaded()\n"
    )
    subprocess.run([sys.executable, "-c", probe], check=True, timeout=60)


def test_a_module_that_declares_another_id_is_refused(monkeypatch: pytest.MonkeyPatch,
                                                      fresh_registry: None) -> None:
    swapped = {**MODULES, Effect.FRICTION: MODULES[Effect.DETENT_TORQUE]}
    monkeypatch.setattr(effects, "MODULES", swapped)
    with pytest.raises(UnknownEffectError, match="does not declare friction"):
        terms(Effect.FRICTION)


def test_an_id_without_a_module_is_a_station_error(monkeypatch: pytest.MonkeyPatch,
                                                  fresh_registry: None) -> None:
    monkeypatch.setattr(effects, "MODULES", {})
    with pytest.raises(UnknownEffectError, match="no module declares"):
        terms(Effect.DETENT_TORQUE)


def test_a_pair_of_rivals_is_written_down_once_and_read_either_way() -> None:
    pairs: dict[frozenset[Effect], str] = {}
    for declared in every():
        for rival, experiment in declared.rivals.items():
            pair = frozenset({declared.effect, rival})
            assert rival is not declared.effect
            assert pair not in pairs, f"{sorted(pair)} declared twice"
            pairs[pair] = experiment
    assert len(pairs) >= 9
    for pair, experiment in pairs.items():
        a, b = sorted(pair)
        assert separating_experiment(a, b) == separating_experiment(b, a) == experiment
    # A pair nobody declared gets the general experiment.
    assert separating_experiment(Effect.DETENT_TORQUE,
                                 Effect.ROTOR_ECCENTRICITY) == DEFAULT_EXPERIMENT


@pytest.mark.parametrize("chain", [ChainKind.RIGID, ChainKind.BELT])
def test_every_combination_of_ids_lays_out_distinct_blocks_that_start_in_their_bounds(
        chain: ChainKind) -> None:
    obs = _obs(1.0 if chain is ChainKind.RIGID else 0.25)
    nominal = layout_for(ModelSpec(chain), obs)
    everything = layout_for(ModelSpec(chain, frozenset(Effect)), obs)
    names = [b.name for b in everything.blocks]
    assert len(names) == len(set(names))
    assert set(nominal.slices) <= set(everything.slices)
    low, high = everything.bounds()
    start = everything.start()
    assert ((low <= start) & (start <= high)).all()
    for effect in Effect:
        own = terms(effect).blocks(ModelSpec(chain, frozenset({effect})), obs)
        # An id's blocks start where the effect is absent (the nominal model again), so
        # the nominal's fit is a start of every larger model.
        assert all(b.name not in nominal.slices for b in own)


def test_only_the_declared_healthy_parts_enter_the_nominal_model() -> None:
    kept = [t.effect for t in every() if t.nominal_blocks is not None]
    assert kept == [Effect.FRICTION]
    assert all(t.healthy_part.startswith("Kept") for t in every()
               if t.nominal_blocks is not None)


MODEL_MODULES = ("model", "motion", "chain", "balance", "jacobian", "floors")
"""The model's own modules: they compose the effects' hooks and name none of them."""


def test_the_model_names_no_effect_and_reads_no_effect_s_parameters() -> None:
    """``Model`` composes its effects' hooks and never branches on one: its modules name
    no id and no parameter an effect adds (its healthy part, friction's levels, is the
    nominal model's own and is read by name)."""
    root = Path(effects.__file__).parent
    added = set()
    for module in MODULES.values():
        if module == "friction":
            continue
        tree = ast.parse((root / f"{module}.py").read_text(encoding="utf-8"))
        added |= {call.args[0].value for call in ast.walk(tree)
                  if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "Block"
                  and call.args and isinstance(call.args[0], ast.Constant)}
    assert {"flux", "dead_time", "clock_drift_ppm", "coupling_fraction"} <= added
    for name in MODEL_MODULES:
        source = (root.parent / f"{name}.py").read_text(encoding="utf-8")
        tree = ast.parse(source)
        strings = {n.value for n in ast.walk(tree) if isinstance(n, ast.Constant)
                   and isinstance(n.value, str)}
        assert not strings & added, (name, strings & added)
        named = {n.attr for n in ast.walk(tree) if isinstance(n, ast.Attribute)
                 and getattr(n.value, "id", None) == "Effect"}
        assert not named, (name, named)
        imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom)}
        assert not {m for m in imported if m and m.startswith("station.diagnosis.effects.")
                    and not m.endswith(".friction")}, (name, imported)
