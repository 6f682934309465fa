"""A line of stations on one database: write throughput, QA's questions at a million
runs, and eight stations calibrating through an outage of the line's server.

- ``store_runs_per_s_*``: 8 processes each record 10,000 finished runs through
  ``begin_run``/``finish_run`` (the calls a calibration records by, with a calibration's
  limit checks, trims, ripple and fit), into one SQLite file and into one PostgreSQL
  server with fsync on, as a line's server runs. The figure is all runs over the wall
  time of all writers.
- ``pg_history_ms_1M_runs`` / ``pg_stats_s_1M_runs`` / ``sqlite_stats_s_1M_runs``: one
  unit's history, and ``station stats`` over everything, in a database of a million
  runs (built in bulk with the triggers off: a million calibrations would take the
  budget to measure nothing). Best of five (three for statistics) after a warm-up.
- ``line_*``: 8 station processes calibrate 25 simulated units each into one
  PostgreSQL; the server is stopped a third of the way in and started again 20 s
  later. Counted afterwards: runs the stations returned that the line lacks (lost),
  runs the line holds twice, spooled runs left unforwarded.

Each process is a fresh interpreter (``spawn``), as stations are separate machines.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import tempfile
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from bench import history_speed
from bench.record import BenchRecord, Goal
from station.core import Trims
from station.rows import RunFilter
from station.runs import LimitCheck, LimitName, RecipeRef, Ripple, Run, RunKind, Verdict
from station.storage import open_store
from station.store import Store

WRITERS = 8
RUNS_PER_WRITER = 10_000
STATIONS = 8
UNITS_PER_STATION = 25
OUTAGE_AFTER_S = 60.0
OUTAGE_S = 20.0
RECIPE_TEXT = 'name = "default"\nversion = "1.0"\n'
RECIPE = RecipeRef("default", "1.0", hashlib.sha256(RECIPE_TEXT.encode()).hexdigest())


def _calibration_like(station_id: int, i: int) -> Run:
    """A run with what a calibration records, before its results."""
    return Run(serial=f"SN{station_id}{i:06d}", kind=RunKind.CALIBRATE, recipe=RECIPE,
               station_id=station_id, operator="bench", software_version="0.1.0",
               bench="sim", started_at=datetime.now(UTC))


def _results(run: Run, i: int) -> None:
    """What a passing calibration fills in: a dozen limit checks, trims, ripple, fit."""
    run.limits = tuple(LimitCheck(name, value, low, high, unit, True)
                       for name, value, low, high, unit in (
        (LimitName.ESTIMATE, 1.0, None, None, ""),
        (LimitName.OFFSET_A, 40.0 + i % 50, -250.0, 250.0, "mA"),
        (LimitName.OFFSET_B, -30.0 + i % 40, -250.0, 250.0, "mA"),
        (LimitName.GAIN_A, 10010.0, 9500.0, 10500.0, "units"),
        (LimitName.GAIN_B, 9990.0, 9500.0, 10500.0, "units"),
        (LimitName.OFFSET_SIGMA, 0.4, None, 2.0, "mA"),
        (LimitName.GAIN_SIGMA, 1.5, None, 10.0, "units"),
        (LimitName.H1_AFTER, 0.02, None, 0.08, "m/s²"),
        (LimitName.H2_AFTER, 0.01, None, 0.08, "m/s²"),
        (LimitName.FIT_R2, 0.995, 0.9, None, ""),
        (LimitName.H1_REDUCTION, 22.0, 6.0, None, "dB"),
    ))
    run.trims_before = Trims(0.0, 0.0, 10000.0, 10000.0)
    run.trims_after = Trims(40.0 + i % 50, -30.0 + i % 40, 10010.0, 9990.0)
    run.trims_estimated = Trims(40.2 + i % 50, -30.1 + i % 40, 10010.3, 9989.8)
    run.uncertainty = Trims(0.3, 0.3, 1.4, 1.4)
    run.trims_stored = True
    run.before, run.after = Ripple(0.35, 0.12), Ripple(0.02, 0.01)
    run.method = "coherent"
    run.fit = {"h1": {"r2": 0.998, "chi2_reduced": 1.1}, "h2": {"r2": 0.991}}
    run.recording = f"/var/station/recordings/{run.serial}/{run.serial}-0001.blf"
    run.recording_sha256 = hashlib.sha256(run.serial.encode()).hexdigest()
    run.motion_s = 6.8
    run.verdict = Verdict.PASS
    run.finished_at = datetime.now(UTC)


def _writer(target: str, station_id: int, runs: int, start_at: float) -> None:
    with open_store(target) as store:
        while time.time() < start_at:  # every writer starts at once
            time.sleep(0.001)
        for i in range(runs):
            run = _calibration_like(station_id, i)
            store.begin_run(run, RECIPE_TEXT)
            _results(run, i)
            store.finish_run(run)


def _throughput(target: str) -> float:
    """Runs per second of WRITERS processes writing at once into ``target``."""
    open_store(target).close()  # the schema first, as a line's first station makes it
    ctx = multiprocessing.get_context("spawn")
    start_at = time.time() + 5.0  # the interpreters start meanwhile
    writers = [ctx.Process(target=_writer, args=(target, n + 1, RUNS_PER_WRITER, start_at))
               for n in range(WRITERS)]
    for w in writers:
        w.start()
    for w in writers:
        w.join()
    wall = time.time() - start_at
    if any(w.exitcode != 0 for w in writers):
        raise RuntimeError(f"a writer failed: {[w.exitcode for w in writers]}")
    with open_store(target) as store:
        count = sum(s.runs for s in store.statistics(RunFilter()))
    if count != WRITERS * RUNS_PER_WRITER:
        raise RuntimeError(f"{count} runs recorded of {WRITERS * RUNS_PER_WRITER}")
    return count / wall


@contextmanager
def _server(*, durable: bool) -> Iterator[Any]:
    from station.testing.postgres import server_binaries, throwaway_cluster  # noqa: PLC0415

    binaries = server_binaries()
    if binaries is None:
        raise RuntimeError("PostgreSQL's server binaries are not installed (Debian: postgresql)")
    with throwaway_cluster(binaries, durable=durable) as cluster:
        yield cluster


def measure_store() -> list[BenchRecord]:
    records = []
    with tempfile.TemporaryDirectory(prefix="station-bench-store-") as tmp:
        lite = _throughput(str(Path(tmp) / "line.db"))
    records.append(BenchRecord("store_runs_per_s_sqlite", lite, "runs/s", 100.0, Goal.AT_LEAST))
    with _server(durable=True) as cluster:
        pg = _throughput(cluster.url())
    records.append(BenchRecord("store_runs_per_s_postgresql", pg, "runs/s", 100.0,
                               Goal.AT_LEAST))
    return records


# -- a million runs ---------------------------------------------------------------------


def _best(repeats: int, call: Any) -> float:
    """The best of ``repeats`` after a warm-up: the others measure the neighbours."""
    call()  # pages into the caches
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return min(times)


_PG_FILL_RUNS = """
INSERT INTO runs (
    serial, kind, recipe_name, recipe_version, recipe_sha256, station_id, operator,
    software_version, bench, started_at, finished_at, verdict, reason,
    trims_before_offset_a_ma, trims_before_offset_b_ma, trims_before_gain_a, trims_before_gain_b,
    trims_after_offset_a_ma, trims_after_offset_b_ma, trims_after_gain_a, trims_after_gain_b,
    trims_estimated_offset_a_ma, trims_estimated_offset_b_ma, trims_estimated_gain_a,
    trims_estimated_gain_b, uncertainty_offset_a_ma, uncertainty_offset_b_ma,
    uncertainty_gain_a, uncertainty_gain_b,
    trims_stored, before_h1, before_h2, after_h1, after_h2, method, fit, warnings,
    recording, recording_sha256, motion_s, run_uuid
)
SELECT
    serial, %(kind)s, %(recipe_name)s, %(recipe_version)s, %(recipe_sha256)s, 1 + i %% 4,
    'operator', '0.1.0', 'sim', started_at, started_at, verdict,
    CASE WHEN verdict = %(fail)s THEN 'offset_sigma_mA above limit' END,
    0.0, 0.0, 10000.0, 10000.0,
    i %% 601 - 300.0, i %% 401 - 200.0, 10000.0 + i %% 301 - 150, 10000.0 - i %% 301 + 150,
    i %% 601 - 300.25, i %% 401 - 200.25, 10000.0 + i %% 301 - 150.5,
    10000.0 - i %% 301 + 150.5, 1.5, 1.25, 0.75, 0.8,
    verdict = %(pass)s, 0.01 + (i %% 97) * 1e-4, 0.005 + (i %% 89) * 1e-4, 0.001, 0.0007,
    'coherent', '{"h1": {"r2": 0.998, "chi2_reduced": 1.1}, "h2": {"r2": 0.991}}', '[]',
    '/var/station/recordings/' || serial || '-' || i || '.blf', lpad(to_hex(i), 64, '0'),
    187.5, ('00000000-0000-4000-8000-' || lpad(to_hex(i), 12, '0'))::uuid
FROM (
    SELECT
        i,
        CASE WHEN i %% %(stride)s = 0 THEN %(target)s
             ELSE 'SN' || (10000 + i %% %(serials)s) END AS serial,
        CASE WHEN i %% %(fail_every)s = 0 OR (i %% %(stride)s = 0 AND i / %(stride)s %% 3 = 0)
             THEN %(fail)s ELSE %(pass)s END AS verdict,
        to_timestamp(%(t0)s + i * %(step)s) AS started_at
    FROM generate_series(1, %(total)s) AS i
) AS s
ORDER BY i
"""

_PG_FILL_LIMITS = """
INSERT INTO limit_checks (run_id, name, position, value, low, high, unit, passed, note)
SELECT run_id, c.name, c.position, c.value, c.low, c.high, c.unit, c.passed, c.note
FROM runs CROSS JOIN (VALUES
    (%(offset_a)s, 0, 12.0::float8, -300.0::float8, 300.0::float8, 'mA', true, ''),
    (%(offset_sigma)s, 1, 4.25, NULL, 2.0, 'mA', false, 'sigma 4.25 > 2'),
    (%(reduction)s, 2, NULL, 6.0, NULL, 'dB', NULL, 'no after measurement')
) AS c (name, position, value, low, high, unit, passed, note)
WHERE runs.verdict = %(fail)s
"""


def _fill_postgresql(url: str) -> None:
    """The SQLite benchmark's million runs (bench.history_speed), in PostgreSQL."""
    import psycopg  # noqa: PLC0415

    open_store(url).close()
    h = history_speed
    stride = (h.RUNS + h.TARGET_RUNS) // h.TARGET_RUNS
    with psycopg.connect(url) as conn:
        # A bulk load by the owner: the append-only triggers would refuse checks added to
        # finished runs, and are not what is measured.
        conn.execute("SET session_replication_role = replica")
        conn.execute("INSERT INTO recipes (sha256, name, version, text, first_used_at) "
                      "VALUES (%s, %s, %s, %s, %s)",
                      (h.recipe_sha256(), h.RECIPE_NAME, h.RECIPE_VERSION, h.RECIPE_TEXT,
                       h.START))
        conn.execute(_PG_FILL_RUNS, {
            "total": h.RUNS + h.TARGET_RUNS, "stride": stride, "target": h.TARGET_SERIAL,
            "serials": h.SERIALS, "fail_every": h.FAIL_EVERY, "t0": h.START.timestamp(),
            "step": h.YEAR_S / (h.RUNS + h.TARGET_RUNS), "kind": RunKind.CALIBRATE.value,
            "pass": Verdict.PASS.value, "fail": Verdict.FAIL.value,
            "recipe_name": h.RECIPE_NAME, "recipe_version": h.RECIPE_VERSION,
            "recipe_sha256": h.recipe_sha256()})
        conn.execute(_PG_FILL_LIMITS, {
            "offset_a": LimitName.OFFSET_A.value, "offset_sigma": LimitName.OFFSET_SIGMA.value,
            "reduction": LimitName.H1_REDUCTION.value, "fail": Verdict.FAIL.value})
    with psycopg.connect(url, autocommit=True) as conn:
        conn.execute("VACUUM ANALYZE")  # as autovacuum would after a day of runs


def measure_million() -> list[BenchRecord]:
    """PostgreSQL's figures (SQLite's are bench.history_speed's, on its own million)."""
    with _server(durable=False) as cluster:
        start = time.perf_counter()
        _fill_postgresql(cluster.url())
        build_s = time.perf_counter() - start
        with open_store(cluster.url()) as store:
            runs = store.history(history_speed.TARGET_SERIAL)
            if len(runs) != history_speed.TARGET_RUNS:
                raise RuntimeError(f"{len(runs)} runs of {history_speed.TARGET_SERIAL}")
            history = _best(5, lambda: store.history(history_speed.TARGET_SERIAL))
            stats = _best(3, lambda: store.statistics(RunFilter()))
            (everything,) = store.statistics(RunFilter())
            if everything.runs != history_speed.RUNS + history_speed.TARGET_RUNS:
                raise RuntimeError(f"statistics over {everything.runs} runs")
    return [
        BenchRecord("pg_history_ms_1M_runs", history * 1000.0, "ms", 10.0, Goal.AT_MOST),
        BenchRecord("pg_stats_s_1M_runs", stats, "s", 1.0, Goal.AT_MOST),
        BenchRecord("pg_db_build_s", build_s, "s", 300.0, Goal.AT_MOST),
    ]


# -- eight stations through an outage ----------------------------------------------------


@dataclass(frozen=True)
class _Made:
    """A run as its station returned it."""

    serial: str
    run_uuid: str
    verdict: str
    spooled: bool


def _station(url: str, station_id: int, home: str, units: int, out: Any) -> None:
    os.environ["STATION_HOME"] = home
    from station.benches import SIM_SPEC  # noqa: PLC0415
    from station.service import Station, calibrate  # noqa: PLC0415

    station = Station(url, replace(SIM_SPEC, station_id=station_id), f"op{station_id}")
    made = []
    for k in range(units):
        run = calibrate(station, f"SN{station_id}{k:03d}").run
        made.append(_Made(run.serial, str(run.run_uuid), str(run.verdict),
                          any("spool" in w for w in run.warnings)))
    out.put(made)


def measure_line() -> list[BenchRecord]:
    from station import spool  # noqa: PLC0415
    from station.pgstore import PostgresStore  # noqa: PLC0415

    with tempfile.TemporaryDirectory(prefix="station-bench-line-") as tmp, \
            _server(durable=True) as cluster:
        url = cluster.url()
        open_store(url).close()
        ctx = multiprocessing.get_context("spawn")
        out = ctx.Queue()
        homes = [Path(tmp) / f"station{n}" for n in range(1, STATIONS + 1)]
        stations = [ctx.Process(target=_station, args=(url, n, str(home), UNITS_PER_STATION,
                                                        out))
                    for n, home in enumerate(homes, start=1)]
        start = time.monotonic()
        for s in stations:
            s.start()
        time.sleep(OUTAGE_AFTER_S)
        cluster.stop()
        time.sleep(OUTAGE_S)
        cluster.start()
        made = [run for _ in stations for run in out.get(timeout=3600)]
        for s in stations:
            s.join()
        wall = time.monotonic() - start
        # A station whose last units fell in the outage forwards its spool with
        # `station sync`, as its operator would.
        left_before_sync = 0
        for home in homes:
            os.environ["STATION_HOME"] = str(home)
            left_before_sync += len(spool.pending())
            if spool.spool_path().exists():
                with Store(spool.spool_path()) as spooled, PostgresStore(url) as line:
                    spool.forward(spooled, line)
        with open_store(url) as line:
            runs = line.query(RunFilter())
        left = 0
        for home in homes:
            os.environ["STATION_HOME"] = str(home)
            left += len(spool.pending())
    on_line = [str(r.run_uuid) for r in runs]
    lost = len({m.run_uuid for m in made} - set(on_line))
    duplicated = len(on_line) - len(set(on_line))
    spooled = sum(m.spooled for m in made)
    if len(made) != STATIONS * UNITS_PER_STATION:
        raise RuntimeError(f"{len(made)} runs made of {STATIONS * UNITS_PER_STATION}")
    return [
        BenchRecord("line_runs_lost", lost, "runs", 0, Goal.AT_MOST),
        BenchRecord("line_runs_duplicated", duplicated, "runs", 0, Goal.AT_MOST),
        BenchRecord("line_spooled_left", left, "runs", 0, Goal.AT_MOST),
        BenchRecord("line_runs_spooled", spooled, "runs", 1, Goal.AT_LEAST),
        # The next calibration with the line back forwards a spool: sync is for the rest.
        BenchRecord("line_runs_left_for_sync", left_before_sync, "runs", 0, Goal.AT_MOST),
        BenchRecord("line_wall_s", wall, "s", 1800.0, Goal.AT_MOST),
    ]
