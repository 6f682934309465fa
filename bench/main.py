"""Run every benchmark and print one JSON line per figure.

Ratios are measured side by side within one run, because these machines are
noisy: a figure compared with a number taken at another time means little.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Iterable

from bench import bench_speed, plant_speed, recording_memory
from bench.record import BenchRecord, Goal

Measure = Callable[[], Iterable[BenchRecord | dict[str, object]]]


def _as_record(item: BenchRecord | dict[str, object]) -> BenchRecord:
    if isinstance(item, BenchRecord):
        return item
    value = float(item["value"])  # type: ignore[arg-type]
    target = float(item["target"])  # type: ignore[arg-type]
    goal = Goal(str(item.get("goal", Goal.AT_LEAST.value)))
    return BenchRecord(str(item["name"]), value, str(item["unit"]), target, goal)


def main() -> int:
    measures: list[Measure] = [plant_speed.measure, bench_speed.measure, recording_memory.measure]
    for measure in measures:
        for item in measure():
            print(_as_record(item).to_json(), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
