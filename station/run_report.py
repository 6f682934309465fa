"""Runs as the outside world reads them: JSON documents and CSV rows.

CLI.md promises the keys scripts rely on (``run_id``, ``serial``,
``verdict``, ``trims``, ``before``, ``after``, ``failed_limits``,
``recording``; in lists ``started_at``, ``recipe``, ``station``); everything
else here is added for people and QA, never instead. ``trims`` is what the
drive holds after the run (null when the run stored none).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from station.advice import next_step
from station.core import Trims
from station.qa import RecipeStatistics
from station.runs import Run, RunKind, utc_iso

if TYPE_CHECKING:
    from station.service import Calibration, Verification


def _trims(t: Trims | None) -> dict[str, float] | None:
    return t.as_dict() if t is not None else None


def run_dict(run: Run) -> dict[str, Any]:
    """The JSON document of one run (``calibrate``, ``history``, ``query``)."""
    return {
        "run_id": run.run_id,
        "run_uuid": None if run.run_uuid is None else str(run.run_uuid),
        "serial": run.serial,
        "kind": run.kind.value,
        "verdict": run.verdict.value if run.verdict is not None else None,
        "reason": run.reason,
        "started_at": utc_iso(run.started_at),
        "finished_at": utc_iso(run.finished_at) if run.finished_at is not None else None,
        "recipe": run.recipe.name,
        "recipe_version": run.recipe.version,
        "recipe_sha256": run.recipe.sha256,
        "station": run.station_id,
        "operator": run.operator,
        "software_version": run.software_version,
        "bench": run.bench,
        "trims": _trims(run.trims_after if run.trims_stored else None),
        "trims_before": _trims(run.trims_before),
        "trims_estimated": _trims(run.trims_estimated),
        "uncertainty": _trims(run.uncertainty),
        "before": run.before.as_dict() if run.before is not None else None,
        "after": run.after.as_dict() if run.after is not None else None,
        "failed_limits": [c.as_dict() for c in run.failed_limits],
        "limits": [c.as_dict() for c in run.limits],
        "method": run.method,
        "fit": run.fit,
        "warnings": list(run.warnings),
        "recording": run.recording,
        "recording_sha256": run.recording_sha256,
        "motion_s": run.motion_s,
        "service_reason": run.service_reason,
        "previous_run_id": run.previous_run_id,
        "next_step": next_step(run),
    }


CSV_COLUMNS: tuple[str, ...] = (
    "run_id", "serial", "kind", "started_at", "finished_at", "verdict", "reason",
    "recipe", "recipe_version", "recipe_sha256", "station", "operator", "software_version",
    "bench", "offset_a_mA", "offset_b_mA", "gain_a", "gain_b",
    "h1_before", "h2_before", "h1_after", "h2_after", "failed_limits",
    "recording", "recording_sha256", "service_reason", "run_uuid",
)
"""One flat row per run, for spreadsheets: trims are those stored in the drive."""


def run_csv_row(doc: dict[str, Any]) -> list[str]:
    """The CSV row of a run's document (``run_dict``): CSV and JSON cannot disagree."""
    trims = doc["trims"] or {}
    before = doc["before"] or {}
    after = doc["after"] or {}
    flat: dict[str, Any] = {
        **{k: doc[k] for k in CSV_COLUMNS if k in doc},
        **{k: trims.get(k) for k in ("offset_a_mA", "offset_b_mA", "gain_a", "gain_b")},
        "h1_before": before.get("h1"),
        "h2_before": before.get("h2"),
        "h1_after": after.get("h1"),
        "h2_after": after.get("h2"),
        "failed_limits": ";".join(c["name"] for c in doc["failed_limits"]),
    }
    return ["" if flat[k] is None else str(flat[k]) for k in CSV_COLUMNS]


def calibration_dict(result: Calibration) -> dict[str, Any]:
    """``calibrate``/``recalibrate``: the run, and for field service what it had before."""
    doc = run_dict(result.run)
    if result.previous is not None or result.run.kind is RunKind.RECALIBRATE:
        previous = result.previous
        doc["previous_trims"] = (
            previous.trims_after.as_dict()
            if previous is not None and previous.trims_after is not None else None
        )
        doc["previous_run_id"] = previous.run_id if previous is not None else None
        doc["drift"] = result.drift.as_dict() if result.drift is not None else None
    return doc


def verify_dict(result: Verification) -> dict[str, Any]:
    """``verify``: the drive's trims against the ones the station last stored."""
    r = result.record
    cal = result.calibration_record
    return {
        "serial": r.serial,
        "match": r.match,
        # The unit has a recorded calibration to compare with (false: never calibrated here).
        "recorded": r.recorded_trims is not None,
        "drive_trims": r.drive_trims.as_dict(),
        "recorded_trims": r.recorded_trims.as_dict() if r.recorded_trims is not None else None,
        "recorded_run_id": r.recorded_run_id,
        "recorded_verdict": result.recorded_verdict.value if result.recorded_verdict else None,
        "calibration_record": {
            "calibrated_at": (
                utc_iso(datetime.fromtimestamp(cal.calibrated_at, UTC))
                if cal.calibrated_at else None
            ),
            "station_id": cal.station_id,
            "count": cal.count,
        },
        "verified_at": utc_iso(r.verified_at),
        "station": r.station_id,
    }


STATS_CSV_COLUMNS = ("recipe", "recipe_version", "recipe_sha256", "runs", "quantity", "n",
                     "mean", "std", "low", "high", "cpk", "cpk_sigma")


def stats_csv_rows(docs: Sequence[dict[str, Any]]) -> list[list[Any]]:
    """``stats --format csv``: one row per recipe version and quantity (empty: none)."""
    return [[d["recipe"], d["recipe_version"], d["recipe_sha256"], d["runs"], name,
             *("" if c[k] is None else c[k]
               for k in ("n", "mean", "std", "low", "high", "cpk", "cpk_sigma"))]
            for d in docs for name, c in d["quantities"].items()]


def stats_dict(s: RecipeStatistics) -> dict[str, Any]:
    """``stats``: one recipe version's verdicts and capability; NaN becomes null."""
    return {
        "recipe": s.recipe.name,
        "recipe_version": s.recipe.version,
        "recipe_sha256": s.recipe.sha256,
        "runs": s.runs,
        "verdicts": {v.value: n for v, n in s.verdicts.items()},
        "quantities": {
            name: {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                   for k, v in {**asdict(c), "cpk_sigma": c.cpk_sigma,
                                "cpk_rough": c.cpk_rough}.items()}
            for name, c in s.quantities.items()
        },
    }
