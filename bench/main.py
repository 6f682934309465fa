"""Run the benchmarks and print one JSON line per figure.

Ratios are measured side by side within one run, because these machines are
noisy: a figure compared with a number taken at another time means little.
``bench/run NAME...`` runs only the named benchmarks (all when none).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path

from bench import (
    analysis_memory,
    analysis_speed,
    bench_speed,
    calibration,
    cli_start,
    diagnosis,
    diagnosis_speed,
    history_speed,
    line,
    plant_speed,
    recording_memory,
    soak,
    suite_time,
)
from bench.analysis_speed import MinuteRecording
from bench.record import BenchRecord, Goal

Measure = Callable[[], Iterable[BenchRecord | dict[str, object]]]


def _as_record(item: BenchRecord | dict[str, object]) -> BenchRecord:
    if isinstance(item, BenchRecord):
        return item
    value = float(item["value"])  # type: ignore[arg-type]
    target = float(item["target"])  # type: ignore[arg-type]
    goal = Goal(str(item.get("goal", Goal.AT_LEAST.value)))
    return BenchRecord(str(item["name"]), value, str(item["unit"]), target, goal)


def _measures(minute: MinuteRecording) -> dict[str, Measure]:
    """Every benchmark by name, in running order."""
    return {
        "cli_start": cli_start.measure,
        "plant_speed": plant_speed.measure,
        "bench_speed": bench_speed.measure,
        "recording_memory": recording_memory.measure,
        # The analysis benches share one recording, made when first needed.
        "analysis_speed": lambda: analysis_speed.measure(minute),
        "analysis_memory": lambda: analysis_memory.measure(minute),
        "history_speed": history_speed.measure,
        "store_speed": line.measure_store,
        "million_postgresql": line.measure_million,
        "line": line.measure_line,
        "calibration": calibration.measure,
        "diagnosis_speed": diagnosis_speed.measure,
        "diagnosis": diagnosis.measure,
        "soak": soak.measure,
        "tests": suite_time.measure,
    }


def main(argv: Sequence[str] | None = None) -> int:
    with tempfile.TemporaryDirectory(prefix="station-bench-") as tmp:
        measures = _measures(MinuteRecording(Path(tmp)))
        parser = argparse.ArgumentParser(prog="bench/run", description=__doc__)
        parser.add_argument(
            "names", nargs="*", metavar="NAME", help=f"run only these of: {', '.join(measures)}"
        )
        names = parser.parse_args(argv).names or list(measures)
        unknown = sorted(set(names) - set(measures))
        if unknown:
            parser.error(f"unknown benchmark(s): {', '.join(unknown)}")
        for name, measure in measures.items():
            if name not in names:
                continue
            for item in measure():
                print(_as_record(item).to_json(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
