"""Peak memory of recording a 60 s run, measured in a child process.

The child is a fresh interpreter, so its peak RSS is the whole cost of a
recording run (interpreter, numpy, canopen, bench, writer) and nothing of the
benchmark harness.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
from pathlib import Path

from bench.analysis_memory import peak_rss_kb
from bench.record import BenchRecord, Goal
from station.core import LoadKind
from station.paths import HOME_ENV
from station.schedules import ScheduleName, SweepPlan, calibration_schedule
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

TARGET_MB = 400.0
RUN_S = 60.0


def _child(out: str) -> None:
    # The calibration sweep stretched to a minute of motion.
    short = SweepPlan()
    holds = 1 + 2 * short.offset_points + short.gain_points  # baseline and the three sweeps
    plan = SweepPlan(dwell_s=(RUN_S - 2 * short.standstill_s) / holds)
    schedule = calibration_schedule(plan)
    request = SimRecordRequest(
        out=Path(out),
        serial=parse_serial("SN60"),
        schedule=ScheduleName.CALIBRATION,
        effects=frozenset(),
        load=LoadKind.DISK,
        loss=0.01,
        truth=Path(out).parent / "truth" / "run.truth.json",
    )
    (Path(out).parent / "truth").mkdir()
    record_schedule(request, schedule)
    # Not ru_maxrss: on Linux a child inherits its parent's peak in it (see analysis_memory).
    print(peak_rss_kb())


def measure() -> list[BenchRecord]:
    records = []
    for suffix in (".blf", ".mf4"):
        with tempfile.TemporaryDirectory() as tmp:
            out = str(Path(tmp) / "rec" / f"run{suffix}")
            Path(out).parent.mkdir()
            done = subprocess.run(
                [sys.executable, "-m", "bench.recording_memory", out],
                check=True,
                env=_env(tmp),
                capture_output=True,
                text=True,
            )
            # The child reports its own peak: RUSAGE_CHILDREN would be the max over all children.
            peak = float(done.stdout.split()[-1]) / 1024.0
            records.append(
                BenchRecord(
                    f"record_60s_peak_memory{suffix.replace('.', '_')}",
                    peak,
                    "MB",
                    TARGET_MB,
                    Goal.AT_MOST,
                )
            )
    return records


def _env(tmp: str) -> dict[str, str]:
    env = dict(os.environ)
    env[HOME_ENV] = str(Path(tmp) / "home")
    return env


if __name__ == "__main__":
    _child(sys.argv[1])
