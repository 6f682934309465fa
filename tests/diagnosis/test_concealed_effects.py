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
import os
from collections.abc import Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from station.core import Effect
from station.schedules import ScheduleName
from station.serials import parse_serial

NONE = "none"
CLASSES = (
    NONE,
    Effect.FLUX_HARMONICS.value,
    Effect.DETENT_TORQUE.value,
    Effect.LOAD_RESONANCE.value,
    Effect.CURRENT_DISTORTION.value,
)
SERIALS = ("SN7101", "SN7102")


@dataclass(frozen=True)
class Case:
    serial: str
    truth: str
    seed: int

    @property
    def label(self) -> str:
        return f"{self.serial}-{self.truth}"


CASES = tuple(
    Case(serial, truth, seed=10 * i + j)
    for i, serial in enumerate(SERIALS)
    for j, truth in enumerate(CLASSES)
)


def _record_and_diagnose(case: Case, root: str) -> dict[str, Any]:
    """One unit, in a worker process: record it, then diagnose the recording alone."""
    # Imported in the worker: each process brings its own simulated bench.
    from station.characterize import diagnose_recording  # noqa: PLC0415
    from station.sim.record import SimRecordRequest, record_simulation  # noqa: PLC0415

    base = Path(root)
    os.environ["STATION_HOME"] = str(base / "home" / case.label)
    out = base / "recordings" / f"{case.label}.blf"
    request = SimRecordRequest(
        out=out,
        serial=parse_serial(case.serial),
        schedule=ScheduleName.CHARACTERIZATION,
        effects=frozenset() if case.truth == NONE else frozenset({Effect(case.truth)}),
        seed=case.seed,
        truth=base / "truth" / f"{case.label}.truth.json",
    )
    record_simulation(request)
    result = diagnose_recording(out, write_report=False)
    return result.as_dict()


@pytest.fixture(scope="module")
def diagnosed(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[Case, dict[str, Any]]]:
    root = tmp_path_factory.mktemp("concealed")
    for folder in ("recordings", "truth", "home"):
        (root / folder).mkdir()
    with ProcessPoolExecutor(max_workers=2) as pool:
        futures = {case: pool.submit(_record_and_diagnose, case, str(root)) for case in CASES}
        results = {case: future.result() for case, future in futures.items()}
    yield results
    print(_confusion(results))


def _named(doc: dict[str, Any]) -> list[tuple[str, list[str]]]:
    return [(e["id"], e.get("cannot_separate_from", [])) for e in doc["effects"]]


def score(truth: str, doc: dict[str, Any]) -> float:
    named = _named(doc)
    if truth == NONE:
        return 1.0 if not named else 0.0
    if len(named) != 1:
        return 0.0
    effect, rivals = named[0]
    if effect == truth and not rivals:
        return 1.0
    return 0.5 if truth in (effect, *rivals) else 0.0


def _confusion(results: dict[Case, dict[str, Any]]) -> str:
    outcomes = sorted({_outcome(doc) for doc in results.values()} | {"none"})
    lines = ["", "confusion matrix (rows: truth, columns: diagnosis)",
             f"{'truth':<20}" + "".join(f"{o[:18]:>20}" for o in outcomes)]
    for truth in CLASSES:
        counts = dict.fromkeys(outcomes, 0)
        for case, doc in results.items():
            if case.truth == truth:
                counts[_outcome(doc)] += 1
        lines.append(f"{truth:<20}" + "".join(f"{counts[o]:>20}" for o in outcomes))
    total = sum(score(c.truth, d) for c, d in results.items())
    lines.append(f"score {total:.1f} / {len(results)}")
    return "\n".join(lines)


def _outcome(doc: dict[str, Any]) -> str:
    named = _named(doc)
    if not named:
        return "none"
    return "+".join("|".join([e, *r]) for e, r in named)


def test_concealed_effects_are_named_correctly_nine_times_in_ten(
    diagnosed: dict[Case, dict[str, Any]],
) -> None:
    total = sum(score(case.truth, doc) for case, doc in diagnosed.items())
    assert total / len(diagnosed) >= 0.9, _confusion(diagnosed)


def test_negative_controls_name_no_effect(diagnosed: dict[Case, dict[str, Any]]) -> None:
    for case, doc in diagnosed.items():
        if case.truth == NONE:
            assert doc["effects"] == [], f"{case.label}: {json.dumps(doc['effects'])[:400]}"


def test_the_extended_model_fits_held_out_data_better_whenever_it_names_an_effect(
    diagnosed: dict[Case, dict[str, Any]],
) -> None:
    for case, doc in diagnosed.items():
        if doc["effects"]:
            assert doc["fit"]["after"] < doc["fit"]["before"], case.label
        else:
            assert doc["fit"]["after"] == doc["fit"]["before"], case.label


def test_a_recording_with_an_effect_is_a_mismatch_located_in_the_map(
    diagnosed: dict[Case, dict[str, Any]],
) -> None:
    for case, doc in diagnosed.items():
        if case.truth != NONE:
            assert doc["mismatch"], case.label
            harmonic = [loc for loc in doc["located"] if loc["kind"] == "harmonic"]
            assert harmonic and all(loc["confidence"] >= 0.999 for loc in harmonic), case.label
            assert {loc["order"] for loc in harmonic} <= set(range(1, doc["orders"] + 1))


def test_the_nominal_model_recovers_the_amplifier_offsets_of_a_clean_unit(
    diagnosed: dict[Case, dict[str, Any]], tmp_path_factory: pytest.TempPathFactory,
) -> None:
    """The nominal fit's optimal offsets are the negated amplifier offsets of the truth."""
    from station.physics.params import derive_unit  # noqa: PLC0415

    for case, doc in diagnosed.items():
        if case.truth != NONE:
            continue
        amp = derive_unit(case.serial, effects=()).amplifier
        trims = doc["nominal"]["optimal_trims"]
        assert trims["offset_a_mA"] == pytest.approx(-amp.offset_a_mA, abs=1.0)
        assert trims["offset_b_mA"] == pytest.approx(-amp.offset_b_mA, abs=1.0)


def test_named_effects_report_physical_parameters(
    diagnosed: dict[Case, dict[str, Any]],
) -> None:
    """A named load resonance comes with its coupling frequency near the truth's."""
    from station.physics.params import derive_unit  # noqa: PLC0415

    for case, doc in diagnosed.items():
        if case.truth != Effect.LOAD_RESONANCE.value:
            continue
        found = [e for e in doc["effects"] if e["id"] == Effect.LOAD_RESONANCE.value]
        assert found, case.label
        coupling = derive_unit(case.serial, effects=(Effect.LOAD_RESONANCE,)).mechanics.coupling
        assert coupling is not None
        assert found[0]["parameters"]["coupling_resonance_hz"] == pytest.approx(
            coupling.resonance_hz, rel=0.1
        )
