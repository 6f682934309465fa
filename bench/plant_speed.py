"""Plant throughput: simulated seconds per wall-clock second on one core.

A calibration or characterization schedule is minutes of bench time; the
simulated bench is only useful if the plant runs many times faster than real
time, with headroom left for the CANopen devices and the station around it.
The target is about one core, so, as ``timeit`` does, the figure is the best
of twenty 0.5-s chunks of a 10-s run: on a shared machine the other chunks
measure the neighbours, not the plant.
"""

from __future__ import annotations

import time
from collections.abc import Iterable

from station.core import Effect, LoadKind, Trims
from station.physics.params import derive_unit
from station.physics.plant import DriveCommand, Plant

SYNC_PERIOD_S = 0.001
ELECTRICAL_HZ = 20.0
AMPLITUDE_mA = 1000.0
SIMULATED_S = 10.0
CHUNKS = 20


def _x_realtime(load: LoadKind, effects: Iterable[Effect]) -> float:
    unit = derive_unit("SN4242", load=load, effects=effects)
    plant = Plant(unit, sync_period_s=SYNC_PERIOD_S)
    m = unit.microsteps
    velocity = ELECTRICAL_HZ * 4 * m
    trims = Trims()
    plant.place_on_trajectory(DriveCommand(True, AMPLITUDE_mA, trims, 0.0, velocity, 0.0, m))
    per_chunk = round(SIMULATED_S / CHUNKS / SYNC_PERIOD_S)
    rates = []
    n = 0
    for _ in range(CHUNKS):
        start = time.perf_counter()
        for _ in range(per_chunk):
            # A command per SYNC, as the simulated drive builds one.
            plant.advance(
                DriveCommand(
                    True, AMPLITUDE_mA, trims, velocity * n * SYNC_PERIOD_S, velocity, 0.0, m
                )
            )
            n += 1
        rates.append(per_chunk * SYNC_PERIOD_S / (time.perf_counter() - start))
    return max(rates)


def measure() -> list[dict[str, object]]:
    cases: list[tuple[str, LoadKind, tuple[Effect, ...], float]] = [
        ("plant_speed_disk", LoadKind.DISK, (), 50.0),
        ("plant_speed_belt", LoadKind.BELT, (), 20.0),
        ("plant_speed_all_effects", LoadKind.BELT, tuple(Effect), 15.0),
        ("plant_speed_disk_all_effects", LoadKind.DISK, tuple(Effect), 15.0),
    ]
    records: list[dict[str, object]] = []
    for name, load, effects, target in cases:
        value = _x_realtime(load, effects)
        records.append(
            {
                "name": name,
                "value": value,
                "unit": "x realtime",
                "target": target,
                "ok": value >= target,
            }
        )
    return records


if __name__ == "__main__":
    for record in measure():
        print(record)
