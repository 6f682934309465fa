"""Runs as the outside world reads them: JSON documents and CSV rows.

CLI.md promises the keys scripts rely on (``run_id``, ``serial``,
``verdict``, ``trims``, ``before``, ``after``, ``failed_limits``,
``recording``; in lists ``started_at``, ``recipe``, ``station``); everything
else here is added for people and QA, never instead. ``trims`` is what the
drive holds after the run (null when the run stored none).
"""

from __future__ import annotations

from typing import Any

from station.core import Trims
from station.runs import Run, utc_iso


def _trims(t: Trims | None) -> dict[str, float] | None:
    return t.as_dict() if t is not None else None


def run_dict(run: Run) -> dict[str, Any]:
    """The JSON document of one run (``calibrate``, ``history``, ``query``)."""
    return {
        "run_id": run.run_id,
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
    }


CSV_COLUMNS: tuple[str, ...] = (
    "run_id", "serial", "kind", "started_at", "finished_at", "verdict", "reason",
    "recipe", "recipe_version", "recipe_sha256", "station", "operator", "software_version",
    "bench", "offset_a_mA", "offset_b_mA", "gain_a", "gain_b",
    "h1_before", "h2_before", "h1_after", "h2_after", "failed_limits",
    "recording", "recording_sha256", "service_reason",
)
"""One flat row per run, for spreadsheets: trims are those stored in the drive."""


def run_csv_row(run: Run) -> list[str]:
    doc = run_dict(run)
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
