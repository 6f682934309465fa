"""The issue's acceptance test: name concealed effects on recordings of the simulated bench.

Each unit is recorded once per session on the simulated bench (the
characterization schedule, every condition held for whole periods) with one
effect switched on, or none (the negative controls), and diagnosed from the
recording alone, exactly as ``station diagnose`` does: the truth goes to a
separate directory the diagnosis never reads. Units and seeds were fixed
before any result was seen, and differ from those the thresholds were tuned
on (SN5xxx, SN6xxx).

Scoring follows the issue: a correct name counts 1, an honest "cannot
separate X from Y" that contains the truth counts ½, anything else 0; on a
negative control any named effect is a miss. ``pytest -s`` prints the
confusion matrix. Recording dominates the time (about 20 s per unit), so two
worker processes record and diagnose in parallel.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor

import pytest

from station.core import Effect
from station.sim.concealed import CLASSES, NO_EFFECT, Case, Trial, confusion, run_trial

SERIALS = ("SN7101", "SN7102")
CASES = tuple(
    Case(serial, truth, seed=10 * i + j)
    for i, serial in enumerate(SERIALS)
    for j, truth in enumerate(CLASSES)
)


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[list[Trial]]:
    root = tmp_path_factory.mktemp("concealed")
    with ProcessPoolExecutor(max_workers=2) as pool:
        trials = list(pool.map(run_trial, CASES, [root] * len(CASES)))
    yield trials
    print("\n" + confusion(trials))


def test_concealed_effects_are_named_correctly_nine_times_in_ten(
    diagnosed: list[Trial],
) -> None:
    total = sum(t.score for t in diagnosed)
    assert total / len(diagnosed) >= 0.9, confusion(diagnosed)


def test_negative_controls_name_no_effect(diagnosed: list[Trial]) -> None:
    for t in diagnosed:
        if t.case.truth == NO_EFFECT:
            assert t.doc["effects"] == [], f"{t.case.label}: {json.dumps(t.doc['effects'])[:400]}"


def test_the_extended_model_fits_held_out_data_better_whenever_it_names_an_effect(
    diagnosed: list[Trial],
) -> None:
    for t in diagnosed:
        fit = t.doc["fit"]
        if t.doc["effects"]:
            assert fit["after"] < fit["before"], t.case.label
        else:
            assert fit["after"] == fit["before"], t.case.label


def test_a_recording_with_an_effect_is_a_mismatch_located_in_the_map(
    diagnosed: list[Trial],
) -> None:
    for t in diagnosed:
        if t.case.truth != NO_EFFECT:
            doc = t.doc
            assert doc["mismatch"], t.case.label
            harmonic = [loc for loc in doc["located"] if loc["kind"] == "harmonic"]
            assert harmonic and all(loc["confidence"] >= 0.999 for loc in harmonic), t.case.label
            assert {loc["order"] for loc in harmonic} <= set(range(1, doc["orders"] + 1))


def test_the_nominal_model_recovers_the_amplifier_offsets_of_a_clean_unit(
    diagnosed: list[Trial],
) -> None:
    """The nominal fit's optimal offsets are the negated amplifier offsets of the truth."""
    from station.physics.params import derive_unit  # noqa: PLC0415

    for t in diagnosed:
        if t.case.truth != NO_EFFECT:
            continue
        amp = derive_unit(t.case.serial, effects=()).amplifier
        trims = t.doc["nominal"]["optimal_trims"]
        assert trims["offset_a_mA"] == pytest.approx(-amp.offset_a_mA, abs=1.0)
        assert trims["offset_b_mA"] == pytest.approx(-amp.offset_b_mA, abs=1.0)


def test_named_effects_report_physical_parameters(diagnosed: list[Trial]) -> None:
    """A named load resonance comes with its coupling frequency near the truth's."""
    from station.physics.params import derive_unit  # noqa: PLC0415

    for t in diagnosed:
        if t.case.truth != Effect.LOAD_RESONANCE.value:
            continue
        found = [e for e in t.doc["effects"] if e["id"] == Effect.LOAD_RESONANCE.value]
        assert found, t.case.label
        coupling = derive_unit(t.case.serial, effects=(Effect.LOAD_RESONANCE,)).mechanics.coupling
        assert coupling is not None
        assert found[0]["parameters"]["coupling_resonance_hz"] == pytest.approx(
            coupling.resonance_hz, rel=0.1
        )

