"""A unit's history from a database of a million runs, fast enough for the operator.

The station shows a unit's past runs (and the trims it should hold) when the
operator scans its label; a line running for years accumulates about a million
runs, and a lookup that scans them would stall every scan. The database is
built with ``Store`` for the schema, then filled in one transaction by one
``INSERT ... SELECT`` over a recursive CTE (a million ``begin_run`` calls would
take the whole benchmark budget to measure nothing of interest). The history
figure is the best of five after a warm-up: the other calls measure the
neighbours on a shared machine.
"""

from __future__ import annotations

import hashlib
import sqlite3
import tempfile
import time
from datetime import UTC, datetime
from pathlib import Path

from bench.record import BenchRecord, Goal
from station.rows import RunFilter
from station.runs import LimitName, RunKind, Verdict, utc_iso
from station.store import Store

RUNS = 1_000_000
SERIALS = 5000
TARGET_RUNS = 12
TARGET_SERIAL = "SN4242"  # outside the SN10000.. range of the other units
FAIL_EVERY = 100  # about 1 % of runs fail
YEAR_S = 365 * 24 * 3600
START = datetime(2024, 1, 1, tzinfo=UTC)
REPEATS = 5
STATS_REPEATS = 3
RECIPE_NAME = "default"
RECIPE_VERSION = "1.0"
RECIPE_TEXT = f'name = "{RECIPE_NAME}"\nversion = "{RECIPE_VERSION}"\n'

_TRIM_COLUMNS = ("offset_a_mA", "offset_b_mA", "gain_a", "gain_b")

# Every row looks like a finished run: real trims, ripple, fit JSON and a recording
# path, so pages hold as many rows as they will on the line.
_FILL_RUNS = f"""
WITH RECURSIVE seq(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM seq WHERE i < :total)
INSERT INTO runs (
    serial, kind, recipe_name, recipe_version, recipe_sha256, station_id, operator,
    software_version, bench, started_at, finished_at, verdict, reason,
    {", ".join(f"trims_before_{c}" for c in _TRIM_COLUMNS)},
    {", ".join(f"trims_after_{c}" for c in _TRIM_COLUMNS)},
    {", ".join(f"trims_estimated_{c}" for c in _TRIM_COLUMNS)},
    {", ".join(f"uncertainty_{c}" for c in _TRIM_COLUMNS)},
    trims_stored, before_h1, before_h2, after_h1, after_h2, method, fit, warnings,
    recording, recording_sha256, motion_s, run_uuid
)
SELECT
    serial, :kind, :recipe_name, :recipe_version, :recipe_sha256, 1 + i % 4, 'operator',
    '0.1.0', 'sim', started_at, started_at, verdict,
    CASE WHEN verdict = :fail THEN 'offset_sigma_mA above limit' END,
    0.0, 0.0, 10000.0, 10000.0,
    i % 601 - 300.0, i % 401 - 200.0, 10000.0 + i % 301 - 150, 10000.0 - i % 301 + 150,
    i % 601 - 300.25, i % 401 - 200.25, 10000.0 + i % 301 - 150.5, 10000.0 - i % 301 + 150.5,
    1.5, 1.25, 0.75, 0.8,
    verdict = :pass, 0.01 + (i % 97) * 1e-4, 0.005 + (i % 89) * 1e-4, 0.001, 0.0007,
    'coherent', '{{"h1": {{"r2": 0.998, "chi2_reduced": 1.1}}, "h2": {{"r2": 0.991}}}}', '[]',
    '/var/station/recordings/' || serial || '-' || i || '.blf', printf('%064x', i), 187.5,
    printf('00000000-0000-4000-8000-%012x', i)
FROM (
    SELECT
        i,
        CASE WHEN i % :stride = 0 THEN :target
             ELSE printf('SN%d', 10000 + i % :serials) END AS serial,
        CASE WHEN i % :fail_every = 0 OR (i % :stride = 0 AND i / :stride % 3 = 0)
             THEN :fail ELSE :pass END AS verdict,
        strftime('%Y-%m-%dT%H:%M:%S', :t0 + i * :step, 'unixepoch') || '.000000Z'
            AS started_at
    FROM seq
)
"""

# Written before the runs (which then get run_id i, the table being empty): limit checks
# can only be added to a run while it is open (db/0002_append_only.sql), and these runs are
# inserted finished. The bulk connection does not enforce foreign keys.
_FILL_LIMITS = """
WITH RECURSIVE seq(i) AS (SELECT 1 UNION ALL SELECT i + 1 FROM seq WHERE i < :total)
INSERT INTO limit_checks (run_id, name, position, value, low, high, unit, passed, note)
SELECT i, column1, column2, column3, column4, column5, column6, column7, column8
FROM seq CROSS JOIN (VALUES
    (:offset_a, 0, 12.0, -300.0, 300.0, 'mA', 1, ''),
    (:offset_sigma, 1, 4.25, NULL, 2.0, 'mA', 0, 'sigma 4.25 > 2'),
    (:reduction, 2, NULL, 6.0, NULL, 'dB', NULL, 'no after measurement')
)
WHERE i % :fail_every = 0 OR (i % :stride = 0 AND i / :stride % 3 = 0)
"""


def build(path: Path) -> None:
    Store(path).close()
    conn = sqlite3.connect(path, isolation_level=None)
    try:
        # A bulk load, not a station: no fsync per page, and the indexes stay in memory.
        conn.execute("PRAGMA synchronous = OFF")
        conn.execute("PRAGMA cache_size = -262144")
        stride = (RUNS + TARGET_RUNS) // TARGET_RUNS
        conn.execute("BEGIN")
        conn.execute(
            "INSERT INTO recipes (sha256, name, version, text, first_used_at) "
            "VALUES (?, ?, ?, ?, ?)",
            (recipe_sha256(), RECIPE_NAME, RECIPE_VERSION, RECIPE_TEXT, utc_iso(START)),
        )
        conn.execute(
            _FILL_LIMITS,
            {
                "total": RUNS + TARGET_RUNS,
                "stride": stride,
                "fail_every": FAIL_EVERY,
                "offset_a": LimitName.OFFSET_A.value,
                "offset_sigma": LimitName.OFFSET_SIGMA.value,
                "reduction": LimitName.H1_REDUCTION.value,
            },
        )
        conn.execute(
            _FILL_RUNS,
            {
                "total": RUNS + TARGET_RUNS,
                "stride": stride,
                "target": TARGET_SERIAL,
                "serials": SERIALS,
                "fail_every": FAIL_EVERY,
                "t0": START.timestamp(),
                "step": YEAR_S / (RUNS + TARGET_RUNS),
                "kind": RunKind.CALIBRATE.value,
                "pass": Verdict.PASS.value,
                "fail": Verdict.FAIL.value,
                "recipe_name": RECIPE_NAME,
                "recipe_version": RECIPE_VERSION,
                "recipe_sha256": recipe_sha256(),
            },
        )
        conn.execute("COMMIT")
    finally:
        conn.close()


def recipe_sha256() -> str:
    return hashlib.sha256(RECIPE_TEXT.encode()).hexdigest()


def measure() -> list[BenchRecord]:
    with tempfile.TemporaryDirectory(prefix="station-bench-history-") as tmp:
        path = Path(tmp) / "station.db"
        start = time.perf_counter()
        build(path)
        build_s = time.perf_counter() - start
        with Store(path) as store:
            history = store.history(TARGET_SERIAL)  # warm-up: pages into the cache
            if len(history) != TARGET_RUNS or not any(run.failed_limits for run in history):
                raise RuntimeError(f"{TARGET_SERIAL} should have {TARGET_RUNS} runs, some failed")
            times = []
            for _ in range(REPEATS):
                start = time.perf_counter()
                store.history(TARGET_SERIAL)
                times.append(time.perf_counter() - start)
            # QA's statistics over the whole year, summed by SQLite (station.statsql).
            store.statistics(RunFilter())
            stats = []
            for _ in range(STATS_REPEATS):
                start = time.perf_counter()
                (everything,) = store.statistics(RunFilter())
                stats.append(time.perf_counter() - start)
            if everything.runs != RUNS + TARGET_RUNS:
                raise RuntimeError(f"statistics over {everything.runs} runs")
    return [
        BenchRecord("history_ms_1M_runs", min(times) * 1000.0, "ms", 50.0, Goal.AT_MOST),
        BenchRecord("sqlite_stats_s_1M_runs", min(stats), "s", 1.0, Goal.AT_MOST),
        BenchRecord("history_db_build_s", build_s, "s", 120.0, Goal.AT_MOST),
    ]
