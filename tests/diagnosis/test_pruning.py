"""Backward elimination of the chosen model: which group goes when the others make it
unnecessary, and which does not when the model it sits in is no physics at all."""

from __future__ import annotations

from collections.abc import Iterable
from types import SimpleNamespace
from typing import Any, cast

import pytest

from station.core import Effect
from station.diagnosis import name as name_module
from station.diagnosis.name import Search, _prune
from station.diagnosis.results import Candidate

FRICTION, COUPLING, RELUCTANCE = (Effect.FRICTION, Effect.LOAD_RESONANCE,
                                  Effect.RELUCTANCE_TORQUE)
GAIN_NEEDED = 100.0
"""What the fake test below asks a group to gain on held-out conditions."""


def _candidate(effects: frozenset[Effect], held: float, rejected: bool) -> Candidate:
    return cast(Candidate, SimpleNamespace(
        effects=effects, held=SimpleNamespace(total=held),
        fit=SimpleNamespace(rejected=("coupling_damping_ratio",) if rejected else ())))


class _Search:
    """Models by their groups with a fixed held-out χ², and a log of refinements."""

    def __init__(self, held: dict[frozenset[Effect], float],
                 rejected: Iterable[frozenset[Effect]] = ()) -> None:
        self.models = {k: _candidate(k, v, k in set(rejected)) for k, v in held.items()}
        self.refined_calls = 0

    def get_all(self, keys: Iterable[tuple[frozenset[Effect], bool]]) -> list[Candidate]:
        return [self.models[effects] for effects, _ in keys]

    def refined(self, tests: list[Any]) -> list[Any]:
        self.refined_calls += 1
        return tests


def _test(smaller: Any, larger: Any) -> SimpleNamespace:
    # The real test's two ways to fail: too small a gain, or a larger model resting where
    # one of its groups is something else.
    gain = smaller.held.total - larger.held.total
    return SimpleNamespace(smaller=smaller, larger=larger, held_gain=gain,
                           significant=gain > GAIN_NEEDED and not larger.fit.rejected)


@pytest.fixture(autouse=True)
def _fake_test(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(name_module, "compare", _test)


def _pruned(search: _Search, *effects: Effect) -> frozenset[Effect]:
    start = search.models[frozenset(effects)]
    return _prune(cast(Search, search), start).effects


def test_a_model_resting_on_a_rejected_bound_loses_the_group_that_gains_least_not_the_first_by_name(
) -> None:
    # Benchmark trial friction@1048096848: the coupling's damping on its ceiling beside
    # friction; by name, friction went first and nothing was named at all.
    search = _Search({frozenset({FRICTION, COUPLING}): 2825.0,
                      frozenset({FRICTION}): 3435.0,
                      frozenset({COUPLING}): 66031.0,
                      frozenset(): 76034.0},
                     rejected=[frozenset({FRICTION, COUPLING})])
    assert _pruned(search, FRICTION, COUPLING) == {FRICTION}


def test_of_several_groups_the_data_do_not_need_the_weakest_goes_first() -> None:
    search = _Search({frozenset({FRICTION, COUPLING, RELUCTANCE}): 1000.0,
                      frozenset({COUPLING, RELUCTANCE}): 1090.0,  # friction gains 90
                      frozenset({FRICTION, RELUCTANCE}): 1050.0,  # the coupling 50
                      frozenset({FRICTION, COUPLING}): 5000.0,
                      frozenset({FRICTION}): 9000.0,
                      frozenset({RELUCTANCE}): 8000.0})
    # Without the coupling, friction gains 7,000 beside reluctance: both stay.
    assert _pruned(search, FRICTION, COUPLING, RELUCTANCE) == {FRICTION, RELUCTANCE}


def test_tests_are_refined_only_when_every_group_looks_needed_as_fitted() -> None:
    needed = _Search({frozenset({FRICTION, RELUCTANCE}): 1000.0,
                      frozenset({FRICTION}): 2000.0, frozenset({RELUCTANCE}): 3000.0})
    assert _pruned(needed, FRICTION, RELUCTANCE) == {FRICTION, RELUCTANCE}
    assert needed.refined_calls == 1
    spare = _Search({frozenset({FRICTION, RELUCTANCE}): 1000.0,
                     frozenset({FRICTION}): 1010.0, frozenset({RELUCTANCE}): 3000.0,
                     frozenset(): 9000.0})
    assert _pruned(spare, FRICTION, RELUCTANCE) == {FRICTION}
    # One refinement: for friction alone against the nominal, once reluctance had gone.
    assert spare.refined_calls == 1
