"""Analysis time of a 60 s recording against python-can merely iterating it.

Reading the log with python-can is a floor no analysis built on it can go
under, and it differs per format several-fold (ASC is text); so
the target is relative: the whole analysis (read, timeline, segments,
harmonics, estimates) may add at most 100 % to a bare ``LogReader`` loop over
the same file. Both are timed alternately in one process, and the ratio is
the median of adjacent pairs, so a neighbour's load hits both sides alike.

``python -m bench.analysis_speed profile LOG`` prints where the analysis
spends its time.
"""

from __future__ import annotations

import cProfile
import gc
import os
import pstats
import statistics
import subprocess
import sys
import time
from collections.abc import Callable
from enum import StrEnum
from pathlib import Path
from typing import Final

import can

from bench.record import BenchRecord, Goal
from bench.tiling import tile_recording
from station.analysis.pipeline import Analysis, analyze
from station.analysis.reader import read_recording
from station.core import LoadKind
from station.paths import HOME_ENV
from station.recording import LogFormat
from station.schedules import Schedule, ScheduleName, SweepPlan, calibration_schedule
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

RUN_S: Final = 60.0
LOSS: Final = 0.01
TARGET_OVERHEAD_PCT: Final = 100.0
PAIRS: Final = {LogFormat.BLF: 5, LogFormat.ASC: 3}
"""Timed (LogReader, analysis) pairs per format; an ASC pass takes 2-3x a BLF one."""

_REPO: Final = Path(__file__).resolve().parents[1]


class Command(StrEnum):
    """What ``python -m bench.analysis_speed COMMAND PATH`` does."""

    RECORD = "record"  # the shared minute, in a child process
    PROFILE = "profile"


def minute_schedule() -> Schedule:
    """The calibration sweep with its dwell stretched to a minute of SYNC time."""
    short = SweepPlan()
    holds = 1 + 2 * short.offset_points + short.gain_points  # baseline and the three sweeps
    return calibration_schedule(SweepPlan(dwell_s=(RUN_S - 2 * short.standstill_s) / holds))


def record_minute(out: Path) -> None:
    """Record the minute on the simulated bench, with the 1 % loss of a busy USB logger."""
    truth = out.parent.parent / "truth"
    truth.mkdir(exist_ok=True)
    request = SimRecordRequest(
        out=out,
        serial=parse_serial("SN60"),
        schedule=ScheduleName.CALIBRATION,
        effects=frozenset(),
        load=LoadKind.DISK,
        loss=LOSS,
        truth=truth / f"{out.stem}.truth.json",
    )
    record_schedule(request, minute_schedule())


class MinuteRecording:
    """The 60 s recording, made on first use and shared by the analysis benches.

    It is recorded in a child process with its own STATION_HOME, so neither
    the simulated unit's EEPROM file nor the bench's threads and memory stay
    behind in the process that times the analysis.
    """

    def __init__(self, directory: Path) -> None:
        self._directory = directory
        self._logs: dict[LogFormat, Path] = {}

    def path(self, log_format: LogFormat = LogFormat.BLF) -> Path:
        if log_format not in self._logs:
            self._logs[log_format] = self._make(log_format)
        return self._logs[log_format]

    def _make(self, log_format: LogFormat) -> Path:
        # One directory per log: a log's metadata is named after its stem.
        folder = self._directory / log_format.name.lower()
        folder.mkdir(parents=True)
        out = folder / f"minute{log_format.value}"
        if log_format is LogFormat.BLF:
            env = dict(os.environ)
            env[HOME_ENV] = str(self._directory / "home")
            run_child(["bench.analysis_speed", Command.RECORD, str(out)], env)
        else:
            # The same frames through python-can's writer for that format,
            # which is what the recorder itself uses.
            tile_recording(self.path(LogFormat.BLF), out, tiles=1)
        return out


def run_child(module_args: list[str], env: dict[str, str] | None = None) -> str:
    """``python -m`` in a fresh interpreter; its stdout, or its stderr in the error."""
    done = subprocess.run(
        [sys.executable, "-m", *module_args],
        check=False,
        cwd=_REPO,
        env=env,
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(module_args)} failed: {done.stderr.strip()[-2000:]}")
    return done.stdout


def iterate_log(path: Path) -> None:
    """The floor: python-can's reader and nothing else."""
    with can.LogReader(str(path)) as reader:
        for _ in reader:
            pass


def analyse_log(path: Path) -> Analysis:
    """What ``station analyze`` computes, without the printing."""
    return analyze(read_recording(path))


def _timed(work: Callable[[], object]) -> float:
    gc.collect()  # the previous pass's garbage is not this pass's cost
    start = time.perf_counter()
    work()
    return time.perf_counter() - start


def measure_format(path: Path, log_format: LogFormat, pairs: int) -> list[BenchRecord]:
    analyse_log(path)  # warm-up: lazy imports, file cache
    reader_s: list[float] = []
    analysis_s: list[float] = []
    for _ in range(pairs):
        reader_s.append(_timed(lambda: iterate_log(path)))
        analysis_s.append(_timed(lambda: analyse_log(path)))
    overhead = statistics.median(b / a for a, b in zip(reader_s, analysis_s, strict=True)) - 1
    reader = statistics.median(reader_s)
    tag = log_format.name.lower()
    return [
        BenchRecord(
            f"analysis_60s_seconds_{tag}",
            statistics.median(analysis_s),
            "s",
            reader * (1 + TARGET_OVERHEAD_PCT / 100),
            Goal.AT_MOST,
        ),
        # The floor has no target of its own beyond reading faster than the bench recorded.
        BenchRecord(f"logreader_60s_seconds_{tag}", reader, "s", RUN_S, Goal.AT_MOST),
        BenchRecord(
            f"analysis_overhead_{tag}", 100 * overhead, "%", TARGET_OVERHEAD_PCT, Goal.AT_MOST
        ),
    ]


def measure(minute: MinuteRecording) -> list[BenchRecord]:
    records: list[BenchRecord] = []
    for log_format, pairs in PAIRS.items():
        records.extend(measure_format(minute.path(log_format), log_format, pairs))
    return records


def profile(path: Path, top: int = 30) -> None:
    """Where one analysis spends its time, by cumulative and by own time."""
    analyse_log(path)
    profiler = cProfile.Profile()
    profiler.runcall(analyse_log, path)
    stats = pstats.Stats(profiler, stream=sys.stdout)
    stats.sort_stats(pstats.SortKey.CUMULATIVE).print_stats(top)
    stats.sort_stats(pstats.SortKey.TIME).print_stats(top)


if __name__ == "__main__":
    if len(sys.argv) != 3 or sys.argv[1] not in set(Command):
        sys.exit(f"usage: python -m bench.analysis_speed {'|'.join(Command)} PATH")
    command, target = Command(sys.argv[1]), Path(sys.argv[2])
    if command is Command.RECORD:
        record_minute(target)
    else:
        profile(target)
