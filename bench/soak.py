"""Soak: 200 calibrations in a row on the simulated bench, with random injected faults.

A line station lives through thousands of runs on a noisy bus; what matters is
that none of them is lost or recorded wrongly, that no drive leaves the
fixture energised, and that no drive leaves it with trims other than those
the database says it holds. Each run here gets zero, one or two faults of
random kind, time and size (``station.sim.faults``), through the whole
station path (``service.calibrate``: bench, procedure, database). Forty units
are calibrated five times each, so a unit that once stored trims must keep
them through every later run that fails.

Checked after each run, against the simulated drive as the station closed it
(``SimBench.at_close``) and the database:

- lost or inconsistent records: no row, an open row, a row that differs from
  what the station returned, an ERROR/ABORTED without reason, a FAIL without
  a failed limit, a PASS without stored trims;
- drives left enabled;
- trims differing from the last stored calibration: the EEPROM against the
  database's last stored run (the factory trims if none), and the RAM against
  the EEPROM unless the drive could no longer be reached and the run says so
  (those are counted apart, as ``unreachable``);
- passes built on spoiled data: a PASS after a fault that corrupts or ends
  the measurement (silence, bus-off, power cycle, sensor saturated or
  unplugged, EEPROM refusal) took effect.
"""

from __future__ import annotations

import logging
import os
import random
import sys
import tempfile
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path
from typing import ClassVar

from bench.record import BenchRecord, Goal
from station import benches
from station.benches import SIM_SPEC
from station.paths import HOME_ENV
from station.rows import RunFilter
from station.runs import Run, Verdict
from station.service import Station, calibrate
from station.sim.bench import SimBench, TrimsLeft
from station.simsettings import Fault, FaultKind, SimSettings
from station.store import Store

RUNS = 200
UNITS = tuple(f"SN{5001 + i}" for i in range(40))
SEED = 2026
LAST_FAULT_S = 16.0
"""Faults are drawn up to here: a default run's motion lasts about 14.5 s, so some land
after the run and must change nothing."""
SPOILING = frozenset({
    FaultKind.DRIVE_SILENT, FaultKind.SENSOR_SILENT, FaultKind.BUS_OFF,
    FaultKind.POWER_CYCLE, FaultKind.SENSOR_SATURATED, FaultKind.SENSOR_UNPLUGGED,
    FaultKind.EEPROM_FAILURE,
})
_COUNTS = {
    FaultKind.SDO_TIMEOUT: (1, 4),  # up to 2 are retried, more end the run
    FaultKind.SENSOR_FRAMES_LOST: (1, 12),
    FaultKind.ERROR_FRAMES: (1, 100),
}


def draw_faults(rng: random.Random) -> tuple[Fault, ...]:
    """None (one run in ten), one, or (one in five) two faults."""
    roll = rng.random()
    number = 0 if roll < 0.1 else 2 if roll > 0.8 else 1
    faults = []
    for _ in range(number):
        kind = rng.choice(list(FaultKind))
        low, high = _COUNTS.get(kind, (1, 1))
        faults.append(Fault(kind, round(rng.uniform(0.0, LAST_FAULT_S), 3),
                            rng.randint(low, high)))
    return tuple(faults)


@dataclass
class Tally:
    verdicts: Counter[str]
    lost_or_inconsistent: int = 0
    left_enabled: int = 0
    trims_differing: int = 0
    unreachable: int = 0
    spoiled_passes: int = 0
    faults_effective: int = 0
    seconds: float = 0.0


def _record_problem(run: Run, store: Store) -> str | None:
    """Why the database's row for ``run`` is wrong or missing (None if it is right)."""
    if run.run_id is None:
        return "no run id"
    try:
        row = store.get_run(run.run_id)
    except Exception as exc:  # any failure to read it back is a lost record
        return f"row {run.run_id} unreadable: {exc}"
    if row.verdict is None or row.finished_at is None:
        return "row left open"
    if (row.verdict, row.reason, row.trims_stored, row.trims_after) != (
            run.verdict, run.reason, run.trims_stored, run.trims_after):
        return "row differs from the run"
    if row.verdict in (Verdict.ERROR, Verdict.ABORTED) and not row.reason:
        return "error without reason"
    if row.verdict is Verdict.FAIL and not any(c.passed is False for c in row.limits):
        return "fail without a failed limit"
    if row.verdict is Verdict.PASS and not (row.trims_stored and row.trims_after):
        return "pass without stored trims"
    return None


class _Watched(SimBench):
    closed: ClassVar[list[SimBench]] = []

    def close(self) -> None:
        super().close()
        if self not in _Watched.closed:
            _Watched.closed.append(self)


def soak(runs: int = RUNS, seed: int = SEED, *, log: bool = True) -> Tally:
    rng = random.Random(seed)
    tally = Tally(Counter())
    # The station opens its simulated benches by this name: watch each one close.
    names = vars(benches)
    original = names["SimBench"]
    names["SimBench"] = _Watched
    logging.disable(logging.CRITICAL)  # the faults are meant to cause errors; keep quiet
    try:
        with tempfile.TemporaryDirectory(prefix="station-soak-") as tmp, _home(Path(tmp)):
            db = Path(tmp) / "station.db"
            start = time.perf_counter()
            for number in range(runs):
                serial = UNITS[number % len(UNITS)]
                faults = draw_faults(rng)
                _Watched.closed.clear()
                spec = replace(SIM_SPEC, sim=SimSettings(faults=faults))
                run = calibrate(Station(db, spec, "soak"), serial).run
                bench = _Watched.closed[-1] if _Watched.closed else None
                flags = _judge(run, bench, db, tally)
                if log:
                    print(f"{number:3d} {serial} {', '.join(map(str, faults)) or '-':50.50} "
                          f"{run.verdict}: {(run.reason or '')[:90]} {' '.join(flags)}",
                          file=sys.stderr, flush=True)
            tally.seconds = time.perf_counter() - start
            with Store(db) as store:
                rows = len(store.query(RunFilter()))
            tally.lost_or_inconsistent += abs(runs - rows)
    finally:
        names["SimBench"] = original
        logging.disable(logging.NOTSET)
    return tally


def _judge(run: Run, bench: SimBench | None, db: Path, tally: Tally) -> list[str]:
    """Count what went wrong with this run; the flags name it for the log line."""
    flags: list[str] = []
    tally.verdicts[run.verdict.value if run.verdict else "none"] += 1
    with Store(db) as store:
        problem = _record_problem(run, store)
        last = store.last_stored(run.serial)
    if problem is not None:
        tally.lost_or_inconsistent += 1
        flags.append(f"RECORD({problem})")
    end = bench.at_close if bench is not None else None
    if bench is None or end is None:
        return flags  # the bench never opened: nothing reached a drive
    effective = {e.fault.kind for e in bench.faults.effects}
    tally.faults_effective += len(effective)
    if end.enabled:
        tally.left_enabled += 1
        flags.append("LEFT-ENABLED")
    left = end.trims_against(last.trims_after if last is not None else None)
    if left is TrimsLeft.EEPROM_DIFFERS:
        tally.trims_differing += 1
        flags.append("EEPROM-DIFFERS")
    elif left is TrimsLeft.RAM_DIFFERS:
        if any("could not restore" in w for w in run.warnings):
            tally.unreachable += 1
            flags.append("(unreachable: RAM not restored)")
        else:
            tally.trims_differing += 1
            flags.append("RAM-DIFFERS")
    if run.verdict is Verdict.PASS and effective & SPOILING:
        tally.spoiled_passes += 1
        flags.append("SPOILED-PASS")
    return flags


@contextmanager
def _home(folder: Path) -> Iterator[None]:
    """STATION_HOME pointed at the soak's folder (simulated EEPROMs) for its duration."""
    saved = os.environ.get(HOME_ENV)
    os.environ[HOME_ENV] = str(folder)
    try:
        yield
    finally:
        if saved is None:
            os.environ.pop(HOME_ENV, None)
        else:
            os.environ[HOME_ENV] = saved


def measure() -> Iterator[BenchRecord]:
    tally = soak()
    runs = sum(tally.verdicts.values())
    yield BenchRecord("soak_runs", runs, "runs", RUNS, Goal.AT_LEAST)
    for verdict in Verdict:
        yield BenchRecord(f"soak_runs_{verdict.value}", tally.verdicts[verdict.value], "runs",
                          0, Goal.AT_LEAST)
    yield BenchRecord("soak_faults_taking_effect", tally.faults_effective, "faults", 1,
                      Goal.AT_LEAST)
    yield BenchRecord("soak_lost_or_inconsistent_records", tally.lost_or_inconsistent, "runs",
                      0, Goal.AT_MOST)
    yield BenchRecord("soak_drives_left_enabled", tally.left_enabled, "runs", 0, Goal.AT_MOST)
    yield BenchRecord("soak_trims_differing_from_last_stored", tally.trims_differing, "runs", 0,
                      Goal.AT_MOST)
    yield BenchRecord("soak_unreachable_drive_ram_not_restored", tally.unreachable, "runs",
                      runs, Goal.AT_MOST)
    yield BenchRecord("soak_passes_on_spoiled_data", tally.spoiled_passes, "runs", 0,
                      Goal.AT_MOST)
    yield BenchRecord("soak_seconds_per_run", tally.seconds / max(runs, 1), "s", 10.0,
                      Goal.AT_MOST)
