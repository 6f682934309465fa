"""Which groups a named one is weighed against: an id that cannot be told apart from
another on the recording is named with that rival, never alone."""

from __future__ import annotations

from types import SimpleNamespace
from typing import cast

from station.core import Effect
from station.diagnosis.name import Search, rival_groups
from station.diagnosis.results import Candidate

DETENT, LAG, COUPLING = Effect.DETENT_TORQUE, Effect.CURRENT_LOOP_LAG, Effect.LOAD_RESONANCE


def _best(*effects: Effect) -> Candidate:
    spec = SimpleNamespace(sensor_bend=False)
    return cast(Candidate, SimpleNamespace(effects=frozenset(effects), spec=spec))


def _search(*fitted: frozenset[Effect]) -> Search:
    return cast(Search, SimpleNamespace(cache={(key, False): object() for key in fitted}))


def test_a_group_fitted_in_the_named_ones_place_is_a_rival_though_the_first_pass_dropped_it(
) -> None:
    # The first pass carried the lag, not the coupling; the second fitted both beside the
    # detent (benchmark trial detent_torque+load_resonance@1372234681).
    search = _search(frozenset({DETENT, LAG}), frozenset({DETENT, COUPLING}))
    rivals = rival_groups(search, _best(DETENT, LAG), LAG, candidates=(LAG, DETENT))
    assert rivals == [COUPLING]


def test_the_first_passes_candidates_come_first_and_unfitted_groups_not_at_all() -> None:
    search = _search(frozenset({DETENT, COUPLING}), frozenset({LAG, Effect.FRICTION}))
    candidates = (Effect.FLUX_HARMONICS, LAG)
    rivals = rival_groups(search, _best(DETENT, LAG), LAG, candidates)
    # Friction was fitted beside the lag, not in its place: no rival to it.
    assert rivals == [Effect.FLUX_HARMONICS, COUPLING]


def test_a_group_already_named_is_no_rival_to_another_named_one() -> None:
    search = _search(frozenset({DETENT, LAG}))
    assert rival_groups(search, _best(DETENT, LAG), LAG, candidates=(DETENT, LAG)) == []
