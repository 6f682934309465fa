"""Concealed-effect trials: record a simulated unit with one effect on, diagnose blind, score.

The acceptance test and the diagnosis benchmark both run these, so they must
record, diagnose and score alike; the rule is the issue's. A correct name
counts 1, an honest "cannot separate X from Y" that contains the truth ½,
anything else 0; on a negative control (no effect) any name is a miss. The
truth file goes to its own folder, and the diagnosis reads the recording only.
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Final

from station.characterize import diagnose_recording
from station.core import Effect
from station.paths import HOME_ENV
from station.schedules import ScheduleName
from station.serials import parse_serial
from station.sim.record import SYNC_PERIOD_S, SimRecordRequest, record_simulation

NO_EFFECT: Final = "none"
CLASSES: Final = (
    NO_EFFECT,
    Effect.FLUX_HARMONICS.value,
    Effect.DETENT_TORQUE.value,
    Effect.LOAD_RESONANCE.value,
    Effect.CURRENT_DISTORTION.value,
)
"""The issue's list: each effect alone, and none."""


@dataclass(frozen=True)
class Case:
    serial: str
    truth: str  # an Effect value, or NO_EFFECT
    seed: int

    @property
    def label(self) -> str:
        return f"{self.serial}-{self.truth}"


@dataclass(frozen=True)
class Trial:
    case: Case
    doc: dict[str, Any]  # what ``station diagnose --json`` prints
    diagnose_s: float  # reading the recording included
    recording_s: float  # simulated time the recording covers

    @property
    def score(self) -> float:
        return score(self.case.truth, self.doc)


def run_trial(case: Case, root: Path) -> Trial:
    """Record ``case`` under ``root`` (recordings, truth and simulated EEPROMs apart) and
    diagnose it. Sets STATION_HOME: run it in a worker process of its own."""
    os.environ[HOME_ENV] = str(root / "home" / case.label)
    out = root / "recordings" / f"{case.label}.blf"
    for folder in (out.parent, root / "truth"):
        folder.mkdir(parents=True, exist_ok=True)
    recorded = record_simulation(SimRecordRequest(
        out=out,
        serial=parse_serial(case.serial),
        schedule=ScheduleName.CHARACTERIZATION,
        effects=frozenset() if case.truth == NO_EFFECT else frozenset({Effect(case.truth)}),
        seed=case.seed,
        truth=root / "truth" / f"{case.label}.truth.json",
    ))
    started = time.perf_counter()
    doc = diagnose_recording(out, write_report=False).as_dict()
    return Trial(case, doc, time.perf_counter() - started, recorded.cycles * SYNC_PERIOD_S)


def named(doc: dict[str, Any]) -> list[tuple[str, list[str]]]:
    """Each named effect with the rivals it cannot be separated from."""
    return [(e["id"], e.get("cannot_separate_from", [])) for e in doc["effects"]]


def score(truth: str, doc: dict[str, Any]) -> float:
    found = named(doc)
    if truth == NO_EFFECT:
        return 1.0 if not found else 0.0
    if len(found) != 1:
        return 0.0
    effect, rivals = found[0]
    if effect == truth and not rivals:
        return 1.0
    return 0.5 if truth in (effect, *rivals) else 0.0


def outcome(doc: dict[str, Any]) -> str:
    """The diagnosis as one confusion-matrix column: ``a|b`` for inseparable rivals."""
    return "+".join("|".join([e, *r]) for e, r in named(doc)) or NO_EFFECT


def confusion(trials: list[Trial]) -> str:
    """Rows: truth; columns: what was named; then the score."""
    columns = sorted({outcome(t.doc) for t in trials} | {NO_EFFECT})
    # Columns as wide as their names: "a|b" and "a+b" must not be cut down to "a".
    width = max(len(c) for c in columns) + 2
    lines = ["confusion matrix (rows: truth, columns: diagnosis)",
             f"{'truth':<20}" + "".join(f"{c:>{width}}" for c in columns)]
    for truth in CLASSES:
        counts = dict.fromkeys(columns, 0)
        for t in trials:
            if t.case.truth == truth:
                counts[outcome(t.doc)] += 1
        lines.append(f"{truth:<20}" + "".join(f"{counts[c]:>{width}}" for c in columns))
    lines.append(f"score {sum(t.score for t in trials):.1f} / {len(trials)}")
    return "\n".join(lines)
