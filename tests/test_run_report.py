"""Runs as scripts read them (station.run_report): the keys CLI.md promises, CSV rows."""

from __future__ import annotations

import csv
import io
import json
import math
from datetime import UTC, datetime, timedelta, timezone

from station.core import Trims
from station.run_report import CSV_COLUMNS, run_csv_row, run_dict
from station.runs import (
    LimitCheck,
    LimitName,
    RecipeRef,
    Ripple,
    Run,
    RunKind,
    Verdict,
    parse_utc_iso,
)

# CLI.md: calibrate gives these at least; history/query give started_at, recipe, station.
CALIBRATE_KEYS = {"run_id", "serial", "verdict", "trims", "before", "after", "failed_limits",
                  "recording"}
LIST_KEYS = {"run_id", "started_at", "verdict", "trims", "recipe", "station"}
TRIM_KEYS = {"offset_a_mA", "offset_b_mA", "gain_a", "gain_b"}

STARTED = datetime(2024, 3, 5, 7, 8, 9, 123456, tzinfo=UTC)
RECIPE = RecipeRef("default", "1", "ab" * 32)
H2_FAILED = LimitCheck(LimitName.H2_AFTER, 0.31, None, 0.25, "m/s²", False)
GAIN_FAILED = LimitCheck(LimitName.GAIN_A, 11600.0, 8500, 11500, "1/10000", False)
H1_PASSED = LimitCheck(LimitName.H1_AFTER, 0.02, None, 0.08, "m/s²", True)
REDUCTION_SKIPPED = LimitCheck(LimitName.H1_REDUCTION, 1.2, 6.0, None, "dB", None, "quiet before")


def new_run(**changes: object) -> Run:
    run = Run(
        serial="SN123",
        kind=RunKind.CALIBRATE,
        recipe=RECIPE,
        station_id=7,
        operator="alice",
        software_version="0.1.0",
        bench="sim",
        started_at=STARTED,
    )
    for key, value in changes.items():
        assert hasattr(run, key), key
        setattr(run, key, value)
    return run


def finished_run() -> Run:
    return new_run(
        run_id=42,
        finished_at=STARTED + timedelta(seconds=95),
        verdict=Verdict.FAIL,
        reason="failed h2_after_mps2 = 0.31 m/s² (limit 0.25)",
        limits=(H1_PASSED, H2_FAILED, REDUCTION_SKIPPED, GAIN_FAILED),
        trims_before=Trims(),
        trims_estimated=Trims(12.4, -40.6, 10150.2, 9849.8),
        trims_after=Trims(12.0, -41.0, 10150.0, 9850.0),
        trims_stored=True,
        uncertainty=Trims(1.0, 1.1, 12.0, 12.0),
        before=Ripple(0.9, 0.7),
        after=Ripple(0.02, 0.31),
        method="coherent",
        recording="/data/runs/SN123-42.blf",
        recording_sha256="cd" * 32,
        warnings=["something to look at"],
    )


def test_run_dict_has_every_key_cli_md_promises_with_the_run_s_values() -> None:
    doc = run_dict(finished_run())
    assert doc.keys() >= CALIBRATE_KEYS | LIST_KEYS
    assert (doc["run_id"], doc["serial"], doc["verdict"]) == (42, "SN123", "fail")
    assert (doc["recipe"], doc["station"]) == ("default", 7)
    assert doc["recording"] == "/data/runs/SN123-42.blf"
    assert doc["before"] == {"h1": 0.9, "h2": 0.7}
    assert doc["after"] == {"h1": 0.02, "h2": 0.31}
    assert parse_utc_iso(doc["started_at"]) == STARTED
    assert doc["started_at"] == "2024-03-05T07:08:09.123456Z"


def test_trims_are_the_four_key_object_of_what_the_drive_stored() -> None:
    doc = run_dict(finished_run())
    assert doc["trims"] == {"offset_a_mA": 12.0, "offset_b_mA": -41.0, "gain_a": 10150.0,
                            "gain_b": 9850.0}
    assert all(isinstance(v, float) for v in doc["trims"].values())
    assert set(doc["trims_estimated"]) == TRIM_KEYS
    assert doc["trims_estimated"]["offset_a_mA"] == 12.4


def test_trims_are_null_when_the_run_stored_none() -> None:
    run = finished_run()
    run.trims_stored = False  # e.g. refused by a limit before writing
    doc = run_dict(run)
    assert doc["trims"] is None
    assert doc["trims_before"] == Trims().as_dict()  # still reported, under its own key


def test_failed_limits_lists_only_the_failed_checks_in_order() -> None:
    doc = run_dict(finished_run())
    assert [c["name"] for c in doc["failed_limits"]] == ["h2_after_mps2", "gain_a"]
    assert doc["failed_limits"][0] == {
        "name": "h2_after_mps2", "value": 0.31, "low": None, "high": 0.25, "unit": "m/s²",
        "passed": False, "note": "",
    }
    assert len(doc["limits"]) == 4


def test_a_run_cut_short_at_the_start_still_gives_every_key() -> None:
    doc = run_dict(new_run(verdict=Verdict.ERROR, reason="drive: no answer"))
    assert doc.keys() >= CALIBRATE_KEYS | LIST_KEYS
    assert doc["run_id"] is None and doc["verdict"] == "error"
    for key in ("trims", "before", "after", "recording", "finished_at"):
        assert doc[key] is None, key
    assert doc["failed_limits"] == []


def test_an_unfinished_run_has_a_null_verdict() -> None:
    assert run_dict(new_run())["verdict"] is None


def test_run_dict_is_json_even_with_infinite_limit_values() -> None:
    run = finished_run()
    run.limits = (LimitCheck(LimitName.H2_REDUCTION, math.inf, 6.0, None, "dB", True),)
    text = json.dumps(run_dict(run), allow_nan=False)
    assert json.loads(text)["limits"][0]["value"] is None


def test_started_at_is_given_in_utc_whatever_the_zone_it_was_taken_in() -> None:
    local = STARTED.astimezone(timezone(timedelta(hours=2)))
    assert run_dict(new_run(started_at=local))["started_at"] == "2024-03-05T07:08:09.123456Z"


# --- CSV --------------------------------------------------------------------------------------


def row_dict(run: Run) -> dict[str, str]:
    row = run_csv_row(run_dict(run))
    assert len(row) == len(CSV_COLUMNS)
    return dict(zip(CSV_COLUMNS, row, strict=True))


def test_csv_columns_are_unique_and_carry_the_list_keys() -> None:
    assert len(set(CSV_COLUMNS)) == len(CSV_COLUMNS)
    assert {"run_id", "started_at", "verdict", "recipe", "station"} <= set(CSV_COLUMNS)
    assert set(CSV_COLUMNS) >= TRIM_KEYS


def test_csv_row_lines_up_with_the_columns() -> None:
    row = row_dict(finished_run())
    assert row["run_id"] == "42"
    assert row["serial"] == "SN123"
    assert row["kind"] == "calibrate"
    assert row["started_at"] == "2024-03-05T07:08:09.123456Z"
    assert row["finished_at"] == "2024-03-05T07:09:44.123456Z"
    assert row["verdict"] == "fail"
    assert row["reason"] == "failed h2_after_mps2 = 0.31 m/s² (limit 0.25)"
    assert (row["recipe"], row["recipe_version"], row["recipe_sha256"]) == ("default", "1",
                                                                            "ab" * 32)
    assert (row["station"], row["operator"], row["software_version"], row["bench"]) == (
        "7", "alice", "0.1.0", "sim",
    )
    assert (row["offset_a_mA"], row["offset_b_mA"], row["gain_a"], row["gain_b"]) == (
        "12.0", "-41.0", "10150.0", "9850.0",
    )
    assert (row["h1_before"], row["h2_before"], row["h1_after"], row["h2_after"]) == (
        "0.9", "0.7", "0.02", "0.31",
    )
    assert row["failed_limits"] == "h2_after_mps2;gain_a"
    assert row["recording"] == "/data/runs/SN123-42.blf"
    assert row["recording_sha256"] == "cd" * 32
    assert row["service_reason"] == ""


def test_csv_row_leaves_unknown_values_empty() -> None:
    row = row_dict(new_run(verdict=Verdict.ABORTED))
    assert row["verdict"] == "aborted"
    for column in ("run_id", "finished_at", "offset_a_mA", "gain_b", "h1_before", "h2_after",
                   "failed_limits", "recording"):
        assert row[column] == "", column


def test_csv_row_of_a_field_service_run_carries_its_reason() -> None:
    run = finished_run()
    run.kind, run.service_reason = RunKind.RECALIBRATE, "noisy, returned by customer"
    row = row_dict(run)
    assert (row["kind"], row["service_reason"]) == ("recalibrate", "noisy, returned by customer")


def test_csv_rows_survive_a_round_trip_through_the_csv_module() -> None:
    runs = [finished_run(), new_run(verdict=Verdict.ERROR, reason='bus: "can0", down')]
    buffer = io.StringIO()
    writer = csv.writer(buffer)
    writer.writerow(CSV_COLUMNS)
    writer.writerows(run_csv_row(run_dict(r)) for r in runs)
    rows = list(csv.DictReader(io.StringIO(buffer.getvalue())))
    assert [r["serial"] for r in rows] == ["SN123", "SN123"]
    assert rows[1]["reason"] == 'bus: "can0", down'
    assert rows[0]["gain_a"] == "10150.0"
