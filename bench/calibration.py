"""The default recipe against the paper's, on the same simulated units in one run,
and the default recipe again with the drive reached over Modbus (``sim-modbus``:
no SYNC angle, so the paper's magnitude method in the recipe's rounds).

Each unit (its own amplifier errors and concealed effects, from its serial)
is calibrated twice, once per recipe, each time from a fresh EEPROM, through
the whole station path (``service.calibrate``: bench, procedure, database).
Motion time is the simulated time the SYNC clock ran, which is what the
calibration costs on a line; accuracy is the distance of each recipe's
estimate from the plant's own optimum (which includes every effect the unit
has), whether or not the recipe's limits then let it be stored; how many
units each recipe passes is reported beside. Units run two at a time, one per
core: each is a separate process with its own virtual bus, and the figures do
not depend on wall-clock time.
"""

from __future__ import annotations

import math
import os
import statistics
import tempfile
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from pathlib import Path

from bench.record import BenchRecord, Goal
from station.benches import SIM_MODBUS_SPEC, SIM_SPEC, BenchSpec
from station.paths import HOME_ENV
from station.physics.optimum import optimal_trims
from station.physics.params import derive_unit
from station.service import Station, calibrate

UNITS = tuple(f"SN{7001 + i}" for i in range(20))
RECIPES = ("default", "paper")
MODBUS = "modbus"
LEGS: dict[str, tuple[str, BenchSpec]] = {
    "default": ("default", SIM_SPEC),
    "paper": ("paper", SIM_SPEC),
    MODBUS: ("default", SIM_MODBUS_SPEC),
}
"""Each leg: the recipe, and the bench it runs on."""
MOTION_RATIO_TARGET = 0.5
OFFSET_TOLERANCE_mA = 3.0
GAIN_TOLERANCE = 30.0


@dataclass(frozen=True)
class Outcome:
    serial: str
    recipe: str  # the leg: a recipe, or the default recipe on the Modbus bench
    verdict: str
    motion_s: float
    offset_error_mA: float  # worst of the two offsets
    gain_error: float
    reason: str


def _calibrate_one(serial: str, leg: str) -> Outcome:
    """One unit, one leg, from a fresh station home (fresh EEPROM, fresh database)."""
    recipe, bench = LEGS[leg]
    with tempfile.TemporaryDirectory(prefix="station-bench-cal-") as home:
        os.environ[HOME_ENV] = home
        station = Station(Path(home) / "station.db", bench, "bench")
        run = calibrate(station, serial, recipe).run
    truth = optimal_trims(derive_unit(serial))
    # The estimate, not the stored trims: a recipe whose limits refuse to store a
    # unit's trims still had an estimate, and each method is judged the same way.
    got = run.trims_estimated
    motion = run.motion_s if run.motion_s is not None else math.nan
    if got is None:
        return Outcome(serial, leg, str(run.verdict), motion, math.inf, math.inf,
                       run.reason or "")
    return Outcome(
        serial,
        leg,
        str(run.verdict),
        motion,
        max(abs(got.offset_a_mA - truth.offset_a_mA), abs(got.offset_b_mA - truth.offset_b_mA)),
        max(abs(got.gain_a - truth.gain_a), abs(got.gain_b - truth.gain_b)),
        run.reason or "",
    )


def _run_all(units: Sequence[str]) -> list[Outcome]:
    jobs = [(serial, leg) for serial in units for leg in LEGS]
    with ProcessPoolExecutor(max_workers=2) as pool:
        return list(pool.map(_calibrate_one, *zip(*jobs, strict=True)))


def _rms(values: Sequence[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values))


def measure(units: Sequence[str] = UNITS) -> list[BenchRecord]:
    outcomes = _run_all(units)
    by_recipe = {r: [o for o in outcomes if o.recipe == r] for r in LEGS}
    modbus = by_recipe[MODBUS]
    default, paper = by_recipe["default"], by_recipe["paper"]
    motion = {r: statistics.mean(o.motion_s for o in by_recipe[r]) for r in RECIPES}
    offset_rms = {r: _rms([o.offset_error_mA for o in by_recipe[r]]) for r in RECIPES}
    gain_rms = {r: _rms([o.gain_error for o in by_recipe[r]]) for r in RECIPES}
    records = [
        BenchRecord("calibration_units", len(units), "units", 20, Goal.AT_LEAST),
        BenchRecord("calibration_motion_s_default", motion["default"], "s/unit",
                    MOTION_RATIO_TARGET * motion["paper"], Goal.AT_MOST),
        BenchRecord("calibration_motion_s_paper", motion["paper"], "s/unit", math.inf,
                    Goal.AT_MOST),
        BenchRecord("calibration_motion_ratio_default_vs_paper",
                    motion["default"] / motion["paper"], "ratio", MOTION_RATIO_TARGET,
                    Goal.AT_MOST),
        # Equal or better accuracy: the default's errors may not exceed the paper's.
        BenchRecord("calibration_offset_error_rms_mA_default", offset_rms["default"], "mA",
                    offset_rms["paper"], Goal.AT_MOST),
        BenchRecord("calibration_offset_error_rms_mA_paper", offset_rms["paper"], "mA",
                    OFFSET_TOLERANCE_mA, Goal.AT_MOST),
        BenchRecord("calibration_gain_error_rms_default", gain_rms["default"], "1/10000",
                    gain_rms["paper"], Goal.AT_MOST),
        BenchRecord("calibration_gain_error_rms_paper", gain_rms["paper"], "1/10000",
                    GAIN_TOLERANCE, Goal.AT_MOST),
        BenchRecord("calibration_offset_error_max_mA_default",
                    max(o.offset_error_mA for o in default), "mA", OFFSET_TOLERANCE_mA,
                    Goal.AT_MOST),
        BenchRecord("calibration_gain_error_max_default", max(o.gain_error for o in default),
                    "1/10000", GAIN_TOLERANCE, Goal.AT_MOST),
        BenchRecord("calibration_offset_error_max_mA_paper",
                    max(o.offset_error_mA for o in paper), "mA", OFFSET_TOLERANCE_mA,
                    Goal.AT_MOST),
        BenchRecord("calibration_gain_error_max_paper", max(o.gain_error for o in paper),
                    "1/10000", GAIN_TOLERANCE, Goal.AT_MOST),
    ]
    records += [
        # Where the drive is reached over Modbus: the same bounds, the magnitude method.
        BenchRecord("calibration_motion_s_modbus", statistics.mean(o.motion_s for o in modbus),
                    "s/unit", math.inf, Goal.AT_MOST),
        BenchRecord("calibration_offset_error_max_mA_modbus",
                    max(o.offset_error_mA for o in modbus), "mA", OFFSET_TOLERANCE_mA,
                    Goal.AT_MOST),
        BenchRecord("calibration_gain_error_max_modbus", max(o.gain_error for o in modbus),
                    "1/10000", GAIN_TOLERANCE, Goal.AT_MOST),
    ]
    for recipe in LEGS:
        passed = sum(o.verdict == "pass" for o in by_recipe[recipe])
        records.append(BenchRecord(f"calibration_pass_rate_{recipe}",
                                   passed / len(by_recipe[recipe]), "fraction", 1.0,
                                   Goal.AT_LEAST))
    return records


if __name__ == "__main__":
    for outcome in _run_all(UNITS):
        print(outcome)
