"""How fast the command line answers: ``--help`` and rejections of bad input.

An operator who mistypes a serial should be told at once, not after the
analysis and bus stacks have loaded (issue 18: 0.5 s on this machine). Each
command is timed as a whole process, as the operator waits for it, interleaved
with ``python -c pass`` so the interpreter's own start, which no code of ours
can shorten, is measured beside it on the same noisy machine. The figure for a
command is the median of its repeats; the worst command is reported against
the target, and its margin over a bare interpreter beside it.
"""

from __future__ import annotations

import os
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Iterator, Sequence

from bench.record import BenchRecord, Goal

REPEATS = 7
TARGET_S = 0.5

COMMANDS: tuple[tuple[str, tuple[str, ...]], ...] = (
    ("help", ("--help",)),
    ("calibrate_help", ("calibrate", "--help")),
    ("bad_serial", ("calibrate", "SN01")),
    ("unknown_recipe", ("calibrate", "SN123", "--recipe", "no-such-recipe")),
    ("missing_bench_file", ("calibrate", "SN123", "--bench", "no-such-bench.toml")),
    ("missing_recording", ("analyze", "no-such-recording.blf")),
    ("unknown_effect", ("sim", "record", "x.blf", "--serial", "SN1", "--schedule",
                        "calibration", "--effect", "no_such_effect")),
    ("bad_date", ("query", "--since", "yesterday")),
    ("unknown_serial_history", ("history", "SN999999")),
)


def _seconds(argv: Sequence[str], env: dict[str, str]) -> float:
    start = time.perf_counter()
    subprocess.run(argv, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                   check=False)
    return time.perf_counter() - start


def measure() -> Iterator[BenchRecord]:
    with tempfile.TemporaryDirectory(prefix="station-cli-") as home:
        env = {**os.environ, "STATION_HOME": home, "COLUMNS": "80"}
        station = [sys.executable, "-m", "station.cli"]
        bare = [sys.executable, "-c", "pass"]
        times: dict[str, list[float]] = {name: [] for name, _ in COMMANDS}
        baseline: list[float] = []
        _seconds([*station, "--help"], env)  # warm the file cache and the .pyc files
        for _ in range(REPEATS):
            for name, args in COMMANDS:
                baseline.append(_seconds(bare, env))
                times[name].append(_seconds([*station, *args], env))
        medians = {name: statistics.median(t) for name, t in times.items()}
        python = statistics.median(baseline)
        for name, value in medians.items():
            yield BenchRecord(f"cli_{name}_s", value, "s", TARGET_S, Goal.AT_MOST)
        worst = max(medians.values())
        yield BenchRecord("cli_worst_s", worst, "s", TARGET_S, Goal.AT_MOST)
        yield BenchRecord("cli_python_pass_s", python, "s", TARGET_S, Goal.AT_MOST)
        # What our imports cost over the bare interpreter, worst command.
        yield BenchRecord("cli_worst_over_python_s", worst - python, "s", TARGET_S - python,
                          Goal.AT_MOST)


if __name__ == "__main__":
    for record in measure():
        print(record.to_json())
