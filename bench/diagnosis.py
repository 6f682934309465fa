"""Diagnosis on concealed effects: the confusion matrix over many units, and its speed.

Every unit is recorded on the simulated bench (characterization schedule)
with one effect of the issue's list switched on, or none, and diagnosed from
the recording alone. Units and seeds here differ from the tests' and from
those the thresholds were tuned on. The time to diagnose a ~50 s
characterization recording (reading it included) is measured in the worker,
one process per core, so it is a one-core figure.
"""

from __future__ import annotations

import os
import statistics
import sys
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import Any

from bench.record import BenchRecord, Goal
from station.characterize import diagnose_recording
from station.core import Effect
from station.paths import HOME_ENV
from station.schedules import ScheduleName
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_simulation

NONE = "none"
CLASSES = (NONE, Effect.FLUX_HARMONICS.value, Effect.DETENT_TORQUE.value,
           Effect.LOAD_RESONANCE.value, Effect.CURRENT_DISTORTION.value)
SERIALS = tuple(f"SN{8201 + i}" for i in range(6))
SCORE_TARGET = 0.9
TIME_TARGET_S = 30.0


def _one(serial: str, truth: str, seed: int, root: str) -> tuple[str, str, dict[str, Any], float,
                                                                   float]:
    base = Path(root)
    label = f"{serial}-{truth}"
    os.environ[HOME_ENV] = str(base / "home" / label)
    out = base / "rec" / f"{label}.blf"
    record_simulation(SimRecordRequest(
        out=out, serial=parse_serial(serial), schedule=ScheduleName.CHARACTERIZATION,
        effects=frozenset() if truth == NONE else frozenset({Effect(truth)}), seed=seed,
        truth=base / "truth" / f"{label}.json",
    ))
    started = time.perf_counter()
    doc = diagnose_recording(out, write_report=False).as_dict()
    elapsed = time.perf_counter() - started
    from station.analysis.reader import read_recording  # noqa: PLC0415

    seconds = read_recording(out).samples * 0.001
    return serial, truth, doc, elapsed, seconds


def _score(truth: str, doc: dict[str, Any]) -> float:
    named = [(e["id"], e.get("cannot_separate_from", [])) for e in doc["effects"]]
    if truth == NONE:
        return 1.0 if not named else 0.0
    if len(named) != 1:
        return 0.0
    effect, rivals = named[0]
    if effect == truth and not rivals:
        return 1.0
    return 0.5 if truth in (effect, *rivals) else 0.0


def measure() -> list[BenchRecord]:
    with tempfile.TemporaryDirectory(prefix="bench-diagnosis-") as tmp:
        for folder in ("rec", "truth", "home"):
            (Path(tmp) / folder).mkdir()
        jobs = [(s, t, 100 * i + j, tmp) for i, s in enumerate(SERIALS)
                for j, t in enumerate(CLASSES)]
        with ProcessPoolExecutor(max_workers=2) as pool:
            results = list(pool.map(_one, *zip(*jobs, strict=True)))
    scores = [_score(truth, doc) for _, truth, doc, _, _ in results]
    negatives = [doc for _, truth, doc, _, _ in results if truth == NONE]
    false_alarms = sum(1 for doc in negatives if doc["effects"])
    worse = sum(1 for _, _, doc, _, _ in results
                if doc["effects"] and doc["fit"]["after"] >= doc["fit"]["before"])
    times = [elapsed for *_, elapsed, _ in results]
    lengths = [seconds for *_, seconds in results]
    records = [
        BenchRecord("diagnosis_named_correctly", statistics.fmean(scores), "fraction",
                    SCORE_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_negative_controls_named", float(false_alarms), "recordings", 0.0,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_named_without_better_fit", float(worse), "recordings", 0.0,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_time_max", max(times), "s", TIME_TARGET_S, Goal.AT_MOST),
        BenchRecord("diagnosis_time_median", statistics.median(times), "s", TIME_TARGET_S,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_recording_length", statistics.fmean(lengths), "s", 45.0,
                    Goal.AT_LEAST),
    ]
    for truth in CLASSES:
        row = [doc for _, t, doc, _, _ in results if t == truth]
        correct = sum(_score(truth, doc) for doc in row)
        records.append(BenchRecord(f"diagnosis_confusion_{truth}", correct / len(row),
                                   "fraction", SCORE_TARGET, Goal.AT_LEAST))
        outcomes: dict[str, int] = {}
        for doc in row:
            key = "+".join(e["id"] + "".join(f"|{r}" for r in e.get("cannot_separate_from", []))
                           for e in doc["effects"]) or NONE
            outcomes[key] = outcomes.get(key, 0) + 1
        print(f"diagnosis truth={truth}: {outcomes}", file=sys.stderr, flush=True)
    return records
