"""The issue's acceptance test: name concealed effects on trials nobody tuned on.

Every class of ``station.sim.concealed`` (a healthy unit, one at the limit, each id,
two-effect combinations, physics no id describes) is drawn once on a seed
above ``TRIAL_SEED_FLOOR``, where nobody developed: a disk or belt unit over
wide ranges, a characterization schedule as someone else might write it,
recorded in process, its truth in a folder the diagnosis never reads, and
diagnosed from the recording alone exactly as ``station diagnose`` does. The
seeds are fixed so that the suite is repeatable: each is derived from its
class's label, never picked by looking at a result; ``STATION_FRESH_TRIALS=1``
draws new ones, as the benchmark always does. A failure prints each trial's
label with its seed, which reproduces it (``Case(cls, seed)``).

One trial per class is a smoke-sized sample, so the score threshold here is
looser than the benchmark's (``bench/run diagnosis``: eight per class and the
issue's targets, out-of-vocabulary physics included, reported met or not);
what must hold on every trial is held on every trial.
``pytest -s`` prints the confusion matrix.
"""

from __future__ import annotations

import json
import math
import os
import statistics
import zlib
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest

import station.sim.concealed as concealed_module
from station.characterize import diagnose_recording
from station.core import Effect, LoadKind, Trims
from station.diagnosis.fit import HeldOut
from station.diagnosis.observations import NotDiagnosable
from station.paths import HOME_ENV
from station.schedules import random_characterization
from station.sim.concealed import (
    CLASSES,
    PLANT_SUBSTEPS,
    REFUSED,
    TRIAL_SEED_FLOOR,
    VISIBLE_EXCESS,
    Case,
    Trial,
    TrialClass,
    TrialPlan,
    cases,
    confusion,
    fresh_seeds,
    named,
    plan_trial,
    record_trial,
    twin_excess,
    weakest_part,
    without_wrong_id,
)
from station.sim.concealed import run_trial as run
from station.sim.inprocess import simulate_timeline
from station.sim.population import draw_unit

pytestmark = pytest.mark.slow  # twenty trials recorded and diagnosed: about five minutes

SMOKE_SCORE = 0.5
"""Mean score over one trial per class below which the diagnosis has surely regressed.
Development trials score about 0.7 (one trial per class has a standard error near 0.1);
the issue's 90 % per class is the benchmark's target, where it is measured on eight
trials per class and reported, met or not."""


def _seeds() -> list[int]:
    if os.environ.get("STATION_FRESH_TRIALS") == "1":
        return fresh_seeds(len(CLASSES))
    return [TRIAL_SEED_FLOOR + zlib.crc32(cls.label.encode()) % 10**8 for cls in CLASSES]


@pytest.fixture(scope="module")
def trials(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Trial]]:
    root = tmp_path_factory.mktemp("concealed")
    drawn = cases(CLASSES, 1, _seeds())
    assert all(case.seed >= TRIAL_SEED_FLOOR for case in drawn)
    with ProcessPoolExecutor(max_workers=2) as pool:
        result = list(pool.map(run, drawn, [root] * len(drawn)))
    yield result
    print("\n" + confusion(result))


@pytest.fixture(scope="module")
def diagnosed(trials: list[Trial]) -> list[Trial]:
    """The trials the diagnosis did not refuse (a refusal scores 0 in the score test)."""
    return [t for t in trials if REFUSED not in t.doc]


def test_concealed_effects_are_named_on_fresh_trials(trials: list[Trial]) -> None:
    assert statistics.fmean(t.score for t in trials) >= SMOKE_SCORE, confusion(trials)


def test_a_clean_unit_is_given_no_effect(diagnosed: list[Trial]) -> None:
    for t in diagnosed:
        if t.case.cls.control:
            assert t.doc["effects"] == [], f"{t.case.label}: {json.dumps(t.doc['effects'])[:400]}"


def test_physics_below_detection_is_given_no_id_it_does_not_have(diagnosed: list[Trial]) -> None:
    """Too weak to name is no licence to name something else: like a clean unit, a trial
    whose concealed physics adds less than ``VISIBLE_EXCESS`` over its twin without it may be
    given no id but its own."""
    for t in diagnosed:
        if not t.detectable:
            assert without_wrong_id(t.case.cls, t.doc), t.case.label


@pytest.mark.parametrize(("entries", "honest"), [
    ([("magnetic_saturation", [])], True),
    ([("reluctance_torque", ["magnetic_saturation", "load_resonance"])], True),
    ([("load_resonance", [])], False),
    ([("load_resonance", ["reluctance_torque"])], False),
    ([("magnetic_saturation", []), ("load_resonance", [])], False),
    ([], True),
])
def test_an_ambiguity_that_holds_the_truth_is_no_wrong_id(
        entries: list[tuple[str, list[str]]], honest: bool) -> None:
    doc = {"effects": [{"id": e, "cannot_separate_from": r} for e, r in entries]}
    assert without_wrong_id(TrialClass(frozenset({Effect.MAGNETIC_SATURATION})), doc) is honest
    assert not without_wrong_id(TrialClass(frozenset({Effect.MAGNETIC_SATURATION})),
                                {REFUSED: "clipped"})


@pytest.mark.parametrize(("effect", "seed", "visible"), [
    # Development trials: a weak saturation on a disk (16 over its twin when written);
    # a disk's coupling at 277 Hz, beside order 7 of the fastest speed, which added nothing
    # while the holds beside the rotor's mode were skipped and 371 once their ringing
    # poles were measured (and is then named); a strong reluctance spring on a disk.
    (Effect.MAGNETIC_SATURATION, 311873, False),
    (Effect.LOAD_RESONANCE, 21, True),
    (Effect.RELUCTANCE_TORQUE, 24, True),
])
def test_a_trials_excess_over_its_clean_twin_says_whether_there_was_anything_to_see(
    effect: Effect, seed: int, visible: bool,
) -> None:
    plan = plan_trial(Case(TrialClass(frozenset({effect})), seed, first_draw=True))
    recorded = simulate_timeline(plan.unit, plan.schedule, seed=seed, loss=plan.loss,
                                 substeps=PLANT_SUBSTEPS)
    excess = twin_excess(plan, recorded)
    if visible:
        assert excess > 2 * VISIBLE_EXCESS
    else:
        # The twin's own noise is the same draw, so what is left is the fits' scatter.
        assert abs(excess) < VISIBLE_EXCESS


def test_a_combination_is_only_as_visible_as_its_weakest_effect() -> None:
    """Development seed 21's coupling is barely within the schedule's reach (above: alone,
    it adds a few hundred to the nominal fit). Beside a detent torque that adds tens of
    thousands over its twin without it (23,502 when written), the pair is only as
    visible as what the coupling adds once the detent is fitted (139 when written)."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.DETENT_TORQUE,
                                                 Effect.LOAD_RESONANCE})), 21,
                              first_draw=True))
    recorded = simulate_timeline(plan.unit, plan.schedule, seed=21, loss=plan.loss,
                                 substeps=PLANT_SUBSTEPS)
    assert twin_excess(plan, recorded) < 20 * VISIBLE_EXCESS


def test_a_pair_of_strong_effects_is_measured_with_the_other_one_fitted() -> None:
    """Flux harmonics beside a rotor eccentricity (development seed 11, a disk): the
    nominal model fits both recordings so badly, each bent its own way, that the pair's
    χ² less its twin's without the eccentricity was −312,884 when measured on it, and a
    missed pair was counted as one with nothing to see. With the flux harmonics fitted on
    both, the eccentricity adds thousands."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.FLUX_HARMONICS,
                                                 Effect.ROTOR_ECCENTRICITY})), 11))
    recorded = simulate_timeline(plan.unit, plan.schedule, seed=11, loss=plan.loss,
                                 substeps=PLANT_SUBSTEPS)
    assert twin_excess(plan, recorded) > 20 * VISIBLE_EXCESS


def test_a_weak_partner_is_kept_when_what_is_left_is_the_strong_effects_own_error(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Flux harmonics of 0.6-0.7 % of Lm1 beside a rotor eccentricity on a disk (seed
    1797214043, drawn fresh by a benchmark run): the flux harmonics took 7 million of the
    nominal χ², and with both fitted 655 was left over the noise on 511 held-out values,
    at orders 4-7 beside the flux's own, where the eccentricity gained 481. Counted as
    physics without an id, that remainder dropped the eccentricity; it is a tenth of a
    permille of what the flux took, well within what a group's own errors may leave.
    Most of it was the eccentric rotor's unbalance (0.2 % of the holding torque), which
    the group did not carry then: with it the eccentricity gains 993 and leaves 314 for
    443 held-out values, the noise's share."""
    monkeypatch.setenv(HOME_ENV, str(tmp_path / "home"))
    # The schedule as that run drew it: redrawn over the whole speed range (since session
    # 50 a redraw stays below the speeds the unit stalled at, and this unit's other
    # schedule leaves no such remainder).
    monkeypatch.setattr(concealed_module, "_ceiling",
                        lambda _schedule, _peaks, below_hz: below_hz)
    plan = plan_trial(Case(TrialClass(frozenset({Effect.FLUX_HARMONICS,
                                                 Effect.ROTOR_ECCENTRICITY})), 1797214043))
    (tmp_path / "truth").mkdir()
    out = record_trial(plan, tmp_path / "unit.blf", tmp_path / "truth" / "unit.json")
    doc = diagnose_recording(out, write_report=False, workers=2).as_dict()
    assert {e for e, _ in named(doc)} == {"flux_harmonics", "rotor_eccentricity"}, doc["effects"]
    left = doc["unexplained"]
    assert not left["significant"] and left["held_out_chi2"] < left["values"], left


@pytest.mark.parametrize(("effects", "refused", "excess"), [
    # The only twin clipped: no measure, and the miss is not excused.
    ({Effect.DETENT_TORQUE}, {0}, -math.inf),
    # Beside a twin that was measured, that one's part.
    ({Effect.DETENT_TORQUE, Effect.FRICTION}, {0}, 123.0),
    ({Effect.DETENT_TORQUE, Effect.FRICTION}, set(), 123.0),
])
def test_a_twin_the_diagnosis_refuses_gives_no_measure_rather_than_ending_the_benchmark(
        monkeypatch: pytest.MonkeyPatch, effects: set[Effect], refused: set[int],
        excess: float) -> None:
    """Bench, session 15: a twin without one effect shook harder than the unit and clipped
    at the unit's range; its refusal ended a 46-minute run. The fits are stood in for:
    what is tested is what a refusal counts as."""
    case = Case(TrialClass(frozenset(effects)), TRIAL_SEED_FLOOR)
    unit = draw_unit(case.seed, load=LoadKind.DISK, effects=case.cls.effects)
    schedule = random_characterization(np.random.default_rng(0), center=Trims())
    plan = TrialPlan(case, unit, schedule, 0.0, Trims())
    recorded = object()
    twins: list[object] = []

    def simulated(*_args: object, **_kwargs: object) -> object:
        twins.append(object())
        return twins[-1]

    def nominal_as_recorded(timeline: object) -> object:
        if timeline is not recorded and twins.index(timeline) in refused:
            raise NotDiagnosable("41 settled segment(s) clipped at the sensor's full scale")
        return timeline

    def held_out_with(nominal: object, _effects: frozenset[Effect],
                      larger: object = None) -> HeldOut:
        total = 1123.0 if nominal is recorded else 1000.0
        return HeldOut(np.array([total]), np.zeros(10))

    monkeypatch.setattr(concealed_module, "simulate_timeline", simulated)
    monkeypatch.setattr(concealed_module, "nominal_as_recorded", nominal_as_recorded)
    monkeypatch.setattr(concealed_module, "_held_out_with", held_out_with)
    monkeypatch.setattr(concealed_module, "_fitted_with", lambda *_args: object())
    measured = twin_excess(plan, recorded)  # type: ignore[arg-type]
    assert len(twins) == len(effects)
    assert measured == excess


@pytest.mark.parametrize(("excess", "detectable"), [
    (None, True),  # named exactly: the diagnosis's own test saw it
    (3 * VISIBLE_EXCESS, True),
    (0.5 * VISIBLE_EXCESS, False),
    (-0.5 * VISIBLE_EXCESS, False),  # within the fits' scatter: nothing to see
    (-1_201_076.0, True),  # a fit failed: no measure, so not excused (bench, session 13)
])
def test_a_miss_is_excused_only_by_an_excess_within_the_fits_scatter(
        excess: float | None, detectable: bool) -> None:
    cls = TrialClass(frozenset({Effect.FRICTION, Effect.SENSOR_CLOCK_DRIFT}))
    trial = Trial(Case(cls, TRIAL_SEED_FLOOR), {"effects": []}, 1.0, 10.0, "disk", excess)
    assert trial.detectable is detectable


@pytest.mark.parametrize(("parts", "excess"), [
    ([23_502.0, 139.0], 139.0),  # only as visible as the weaker effect
    ([12.0, -1_201_076.0], 12.0),  # a failed fit beside an invisible effect: excused
    ([-478.0, -1_201_076.0], -1_201_076.0),  # nothing measured: the miss stands
])
def test_a_combination_is_as_visible_as_the_weakest_effect_that_was_measured(
        parts: list[float], excess: float) -> None:
    assert weakest_part(parts) == excess


def test_the_extended_model_fits_held_out_data_better_whenever_it_models_more(
    diagnosed: list[Trial],
) -> None:
    """An effect named, or physics with no id modelled (a bent sensor transfer), must
    lower the held-out residual; with neither, the extended model is the nominal one."""
    for t in diagnosed:
        fit = t.doc["fit"]
        modelled = any(f["parameter"] == "sensor_bend" for f in t.doc["findings"])
        if t.doc["effects"] or modelled:
            assert fit["after"] < fit["before"], t.case.label
        else:
            assert fit["after"] == fit["before"], t.case.label


def test_no_nominal_parameter_at_a_bound_is_reported_as_a_result(diagnosed: list[Trial]) -> None:
    """A parameter pressed against its limit becomes a finding and a mismatch."""
    for t in diagnosed:
        doc = t.doc
        pushed = [name for name, state in doc["nominal"]["states"].items()
                  if state["state"] == "pushed_past_limit"]
        if pushed:
            assert doc["mismatch"], t.case.label
            assert {f["parameter"] for f in doc["findings"]} >= set(pushed), t.case.label


def _keys(value: object) -> Iterator[str]:
    if isinstance(value, dict):
        for key, item in value.items():
            yield str(key)
            yield from _keys(item)
    elif isinstance(value, list):
        for item in value:
            yield from _keys(item)


def test_every_named_effect_carries_evidence_and_parameters_with_sigma(
    diagnosed: list[Trial],
) -> None:
    for t in diagnosed:
        for effect in t.doc["effects"]:
            assert effect["parameters"], t.case.label
            assert any("sigma" in key for key in _keys(effect["parameters"])), (t.case.label,
                                                                                effect)
            cells = effect["evidence"]
            if cells:  # the located cells it explains: the strongest must improve
                assert cells[0]["chi2_after"] < cells[0]["chi2_before"], (t.case.label, effect)


def test_the_whole_schedule_is_used_or_its_skipping_explained(diagnosed: list[Trial]) -> None:
    for t in diagnosed:
        doc = t.doc
        assert len(doc["conditions"]) >= 3, t.case.label
        for skipped in doc["skipped"]:
            assert skipped["reason"], t.case.label
