"""Diagnosis on concealed physics, on trials nobody tuned on: the issue's targets.

Every class of ``station.sim.concealed`` (a clean unit, each vocabulary id,
two-effect combinations, two effects no id describes) is drawn
``PER_CLASS`` times on fresh seeds above ``TRIAL_SEED_FLOOR`` (new every run:
the seeds the diagnosis was developed on are never the ones reported),
recorded in process and diagnosed from the recording alone, two worker
processes side by side, each diagnosis in its own process: the time per
recording measured there (reading the recording included) is a one-core
figure. Then ``ALONE_SAMPLE`` of the recordings, evenly spread over the
classes, are diagnosed again one at a time as ``station diagnose`` runs on
this machine, its models fitted side by side on every core: that is the time
per recording an engineer waits, and the answer must be the same.

A class's "named exactly" counts its detectable trials: those named exactly, and
the others whose concealed physics added at least ``VISIBLE_EXCESS`` (50) to the
nominal fit's held-out χ² over a twin of the unit without it (same schedule,
same noise; for a combination, each effect over the twin without that one, both
fitted with the other effect's group; a belt's coupling leaves its compliance in the
twin's belt: ``station.sim.concealed.twin_excess``, ``nominal_equivalent``;
an excess below −50 is a failed fit, not invisible physics, and counts as a miss; so
does a twin the diagnosis refuses).
The trials within ±50 are counted apart and must not be given a wrong id (an
ambiguity whose rivals hold a concealed effect is none: ``without_wrong_id``); the
share over every trial is reported too.
A control (a healthy unit: its bearings' Coulomb friction up to CLI.md's limit and
viscous drag, one class drawn just under the limit) must be given no id and no mismatch:
a residual flagged on a healthy unit is a false alarm, counted apart from the ids.

``STATION_BENCH_DIAGNOSIS_PER_CLASS`` lowers the trial count for a quick look;
the figures a note quotes come from the default.
"""

from __future__ import annotations

import functools
import os
import statistics
import sys
import tempfile
import time
import traceback
from concurrent.futures import Future, ProcessPoolExecutor
from pathlib import Path
from typing import Any

from bench.record import BenchRecord, Goal
from station.characterize import diagnose_recording, diagnosis_workers
from station.errors import StationError
from station.paths import HOME_ENV
from station.sim.concealed import (
    CLASSES,
    REFUSED,
    Case,
    Trial,
    cases,
    confusion,
    describe,
    fresh_seeds,
    named,
    run_trial,
    trial_recording,
    without_wrong_id,
)

PER_CLASS = 8
NAMED_TARGET = 0.9
"""Each class named exactly (score 1) in at least this share of its trials."""
CONTROL_TARGET = 0.95
"""Healthy units (bearing friction up to CLI.md's limit, viscous drag) given no id in at
least this share."""
CONTROL_MISMATCH_TARGET = 0.9
"""Healthy units left without a mismatch in at least this share."""
UNNAMED_TARGET = 0.9
"""Physics outside the vocabulary given no id in at least this share."""
TIME_TARGET_S = 30.0
"""A recording diagnosed at worst within this long, on one core or on every core."""
MEDIAN_TARGET_S = 12.0
"""...and at the median within this long on one core: twice as fast as issue 90 found it."""
ALONE_SAMPLE = 10
"""Recordings diagnosed again alone, on every core, for the time an engineer waits."""
WALL_TARGET_MIN = 40.0
UNDETECTABLE_SHARE = 0.1
"""At most this share of the trials with concealed physics may fall below detection: more,
and the population's ranges would be drawing effects nobody could see."""


def _exact(trials: list[Trial]) -> float:
    return statistics.fmean(1.0 if t.score == 1.0 else 0.0 for t in trials) if trials else 1.0


def _share_without(trials: list[Trial], key: str) -> float:
    """Share of ``trials`` whose diagnosis found nothing under ``key`` (no effects, no
    mismatch); a refused diagnosis has no such key and counts as having found it."""
    return (statistics.fmean(0.0 if t.doc.get(key, True) else 1.0 for t in trials)
            if trials else 1.0)


def _alone(trials: list[Trial], root: Path) -> list[tuple[float, bool]]:
    """Seconds to diagnose each of a spread sample again, alone on every core, and
    whether it gave the answer the one-process diagnosis gave."""
    step = max(1, len(trials) // ALONE_SAMPLE)
    os.environ[HOME_ENV] = str(root / "home" / "alone")
    workers = diagnosis_workers()
    out = []
    for trial in trials[::step][:ALONE_SAMPLE]:
        started = time.perf_counter()
        try:
            doc = diagnose_recording(trial_recording(trial.case, root), write_report=False,
                                     workers=workers).as_dict()
        except StationError as exc:
            doc = {REFUSED: str(exc)}
        out.append((time.perf_counter() - started, _answer(doc) == _answer(trial.doc)))
    return out


def _result(case: Case, future: Future[Trial]) -> Trial | None:
    """The trial, or None with its crash printed under the case's label: a fresh seed is
    drawn once, and the label (``Case(cls, seed)``) is all that reproduces it. A crash is
    counted, not raised: one plant that overflowed ended a run of 85 minutes and took
    150 measured trials with it."""
    try:
        return future.result()
    except Exception:
        print(f"crashed {case.label}:\n{traceback.format_exc()}", file=sys.stderr, flush=True)
        return None


def _progress(case: Case, future: Future[Trial]) -> None:
    """One line per trial as it finishes: an hour's run that is stopped early still
    leaves what it measured."""
    if future.exception() is None:
        trial = future.result()
        print(f"trial {case.label}: score {trial.score:.2f} in {trial.diagnose_s:.1f} s",
              file=sys.stderr, flush=True)


def _answer(doc: dict[str, Any]) -> tuple[Any, ...]:
    """What a diagnosis concluded: its ids with their rivals, the mismatch, a refusal."""
    if REFUSED in doc:
        return (REFUSED, doc[REFUSED])
    return (tuple(sorted((e, tuple(r)) for e, r in named(doc))), doc["mismatch"],
            doc["fit"]["after_chi2"])


def _per_class() -> int:
    raw = os.environ.get("STATION_BENCH_DIAGNOSIS_PER_CLASS")
    return PER_CLASS if raw is None else max(1, int(raw))


def measure() -> list[BenchRecord]:
    per_class = _per_class()
    drawn = cases(CLASSES, per_class, fresh_seeds(per_class * len(CLASSES)))
    started = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-diagnosis-") as tmp:
        with ProcessPoolExecutor(max_workers=2) as pool:
            futures = [pool.submit(run_trial, case, Path(tmp)) for case in drawn]
            for case, future in zip(drawn, futures, strict=True):
                future.add_done_callback(functools.partial(_progress, case))
            results = [_result(case, future) for case, future in zip(drawn, futures, strict=True)]
        trials = [t for t in results if t is not None]
        alone = _alone(trials, Path(tmp))
    wall_min = (time.perf_counter() - started) / 60.0
    print(confusion(trials), file=sys.stderr, flush=True)
    detectable = [t for t in trials if t.detectable]
    hidden = [t for t in trials if not t.detectable]
    for t in trials:  # every miss, reproducible from its label (Case(cls, seed))
        if REFUSED in t.doc:
            continue
        if t.score < 1.0:
            kind = "miss" if t.detectable else "below detection"
            print(f"{kind}: {describe(t)}", file=sys.stderr, flush=True)
        elif t.case.cls.control and t.doc["mismatch"]:
            # Scored 1 (no id), yet counted against the controls' mismatch figure.
            print(f"false alarm: {describe(t)}", file=sys.stderr, flush=True)
    records: list[BenchRecord] = []
    for cls in CLASSES:
        mine = [t for t in detectable if t.case.cls == cls]
        records.append(BenchRecord(f"diagnosis_named_exactly_{cls.label}", _exact(mine),
                                   "fraction", NAMED_TARGET, Goal.AT_LEAST))
    refused = [t for t in trials if REFUSED in t.doc]
    for t in refused:  # each reproducible from its label (Case(cls, seed))
        print(f"refused {t.case.label}: {t.doc[REFUSED]}", file=sys.stderr, flush=True)
    done = [t for t in trials if REFUSED not in t.doc]
    controls = [t for t in trials if t.case.cls.control]
    unnamed = [t for t in trials if t.case.cls.out_of_vocabulary]
    naming = [t for t in done if t.doc["effects"]]
    concealing = [t for t in trials if not t.case.cls.control]
    records += [
        BenchRecord("diagnosis_named_exactly_all_classes", _exact(detectable),
                    "fraction", NAMED_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_named_exactly_every_trial", _exact(trials),
                    "fraction", NAMED_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_below_detection", float(len(hidden)), "trials",
                    UNDETECTABLE_SHARE * len(concealing), Goal.AT_MOST),
        BenchRecord("diagnosis_below_detection_without_wrong_id",
                    statistics.fmean(1.0 if without_wrong_id(t.case.cls, t.doc) else 0.0
                                    for t in hidden)
                    if hidden else 1.0, "fraction", CONTROL_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_score_mean", statistics.fmean(t.score for t in trials),
                    "fraction", NAMED_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_controls_without_id", _share_without(controls, "effects"),
                    "fraction", CONTROL_TARGET, Goal.AT_LEAST),
        # A clean unit flagged with a residual no id explains is a false alarm too: the
        # issue's first complaint, and what short holds beside a lightly damped mode caused
        # on clean twins until their ringing poles were measured (README, item 2); the id
        # figure above cannot see it.
        BenchRecord("diagnosis_controls_without_mismatch", _share_without(controls, "mismatch"),
                    "fraction", CONTROL_MISMATCH_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_out_of_vocabulary_without_id", _share_without(unnamed, "effects"),
                    "fraction", UNNAMED_TARGET, Goal.AT_LEAST),
        BenchRecord("diagnosis_named_with_better_held_out_fit",
                    statistics.fmean(1.0 if t.doc["fit"]["after"] < t.doc["fit"]["before"]
                                     else 0.0 for t in naming) if naming else 1.0,
                    "fraction", 1.0, Goal.AT_LEAST),
        BenchRecord("diagnosis_refused_characterizations", float(len(refused)), "trials", 0.0,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_crashed_trials", float(len(results) - len(trials)), "trials",
                    0.0, Goal.AT_MOST),
        BenchRecord("diagnosis_time_median", statistics.median(s for s, _ in alone), "s",
                    TIME_TARGET_S, Goal.AT_MOST),
        BenchRecord("diagnosis_time_max", max(s for s, _ in alone), "s",
                    TIME_TARGET_S, Goal.AT_MOST),
        BenchRecord("diagnosis_alone_same_answer",
                    statistics.fmean(1.0 if same else 0.0 for _, same in alone),
                    "fraction", 1.0, Goal.AT_LEAST),
        BenchRecord("diagnosis_time_one_core_median",
                    statistics.median(t.diagnose_s for t in trials), "s", MEDIAN_TARGET_S,
                    Goal.AT_MOST),
        BenchRecord("diagnosis_time_one_core_max", max(t.diagnose_s for t in trials), "s",
                    TIME_TARGET_S, Goal.AT_MOST),
        BenchRecord("diagnosis_trials", float(len(trials)), "trials",
                    float(8 * len(CLASSES)), Goal.AT_LEAST),
        BenchRecord("diagnosis_wall_time", wall_min, "min", WALL_TARGET_MIN, Goal.AT_MOST),
    ]
    return records
