"""Diagnosis on concealed effects: the confusion matrix over many units, and its speed.

Every unit is recorded on the simulated bench (characterization schedule)
with one effect of the issue's list switched on, or none, and diagnosed from
the recording alone (``station.sim.concealed``, as the acceptance test does).
Units and seeds here differ from the tests' and from those the thresholds
were tuned on. The time to diagnose a ~50 s characterization recording
(reading it included) is measured in the worker, one process per core, so it
is a one-core figure.
"""

from __future__ import annotations

import statistics
import sys
import tempfile
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from bench.record import BenchRecord, Goal
from station.sim.concealed import CLASSES, NO_EFFECT, Case, confusion, run_trial

SERIALS = tuple(f"SN{8201 + i}" for i in range(6))
SCORE_TARGET = 0.9
TIME_TARGET_S = 30.0
RECORDING_S = 45.0
"""The issue's figure is for a 50 s characterization; shorter ones would flatter the time."""


def measure() -> list[BenchRecord]:
    cases = [Case(s, t, 100 * i + j) for i, s in enumerate(SERIALS) for j, t in enumerate(CLASSES)]
    with (tempfile.TemporaryDirectory(prefix="bench-diagnosis-") as tmp,
          ProcessPoolExecutor(max_workers=2) as pool):
        trials = list(pool.map(run_trial, cases, [Path(tmp)] * len(cases)))
    print(confusion(trials), file=sys.stderr, flush=True)
    false_alarms = sum(1 for t in trials if t.case.truth == NO_EFFECT and t.doc["effects"])
    worse = sum(1 for t in trials
                if t.doc["effects"] and t.doc["fit"]["after"] >= t.doc["fit"]["before"])
    times = [t.diagnose_s for t in trials]
    records = [
        BenchRecord("diagnosis_named_correctly", statistics.fmean(t.score for t in trials),
                    "fraction", SCORE_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_negative_controls_named", float(false_alarms), "recordings", 0.0,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_named_without_better_fit", float(worse), "recordings", 0.0,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_time_max", max(times), "s", TIME_TARGET_S, Goal.AT_MOST),
        BenchRecord("diagnosis_time_median", statistics.median(times), "s", TIME_TARGET_S,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_recording_length", statistics.fmean(t.recording_s for t in trials),
                    "s", RECORDING_S, Goal.AT_LEAST),
    ]
    for truth in CLASSES:
        row = [t.score for t in trials if t.case.truth == truth]
        records.append(BenchRecord(f"diagnosis_confusion_{truth}", statistics.fmean(row),
                                   "fraction", SCORE_TARGET, Goal.AT_LEAST))
    return records
