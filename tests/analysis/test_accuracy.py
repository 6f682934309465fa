"""The issue's acceptance test: trims from simulated recordings against the known optimum.

Each unit is recorded once per session (the paper's sweeps: offsets ±500 mA in
11 points, gains 7000..13000 in 11 points, 1 s per point; 1 % of frames lost;
sensor noise drawn in 150..400 µg/√Hz), in every log format, then analysed
with ``read_recording`` + ``analyze`` exactly as ``station analyze`` does. The
truth is the optimum the plant computes with every effect the unit has.

The recordings are made in process (``record_in_process``), not over the virtual
bus: what is tested here is the analysis, and the bus's threads deliver the drive's
and the sensor's frames in an order that varies from run to run, so a lossy logger
dropped different frames each time and the same seed gave estimates up to 4 mA
apart (issue 19). Without loss the two paths give the same samples
(``tests/sim/test_inprocess.py``); the bus path keeps its own tests.

``pytest -s`` prints the table of errors.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cache
from pathlib import Path

import numpy as np
import pytest

from station.analysis.pipeline import Analysis, AnalysisOptions, analyze
from station.analysis.reader import read_recording
from station.core import LoadKind, Method, MethodChoice, Trims
from station.physics.params import derive_unit
from station.recording import LogFormat
from station.schedules import SweepPlan, calibration_schedule
from station.sim.inprocess import record_in_process
from station.sim.record import SYNC_PERIOD_S, operating_optimum

OFFSET_TOLERANCE_mA = 3.0
GAIN_TOLERANCE = 30.0
DRIFT_GAIN_TOLERANCE = 60.0
"""Known limit: a sensor whose clock drifts (sample-and-hold at SYNC) delays each sample
by a sawtooth 0..1 ms, which turns H2's phase by up to 14° differently at each point; the
coherent split then misses by up to about 40. Modelling that delay is issue 5's work."""
LOSS = 0.01
NOISE_RANGE_UG = (150.0, 400.0)
PLAN = SweepPlan()  # the paper's sweeps: 1 s per point
FORMATS = (LogFormat.BLF, LogFormat.ASC, LogFormat.MF4, LogFormat.CSV, LogFormat.CANDUMP)


@dataclass(frozen=True)
class Unit:
    """One simulated unit on the bench, chosen before any result was seen."""

    serial: str
    load: LoadKind
    log_format: LogFormat
    seed: int
    noise_ug: float

    @property
    def label(self) -> str:
        return f"{self.serial}-{self.load.value}{self.log_format.value}"


def _units() -> tuple[Unit, ...]:
    """Six disk and six belt units, alternating, the formats spread over both loads."""
    rng = np.random.default_rng(20240603)
    return tuple(
        Unit(
            serial=f"SN{3101 + i}",
            load=LoadKind.DISK if i % 2 == 0 else LoadKind.BELT,
            log_format=FORMATS[i % len(FORMATS)],
            seed=i + 1,
            noise_ug=float(rng.uniform(*NOISE_RANGE_UG)),
        )
        for i in range(12)
    )


UNITS = _units()


@dataclass(frozen=True)
class Recorded:
    unit: Unit
    recording: Path
    optimum: Trims
    effects: tuple[str, ...]


@dataclass(frozen=True)
class Bench:
    recorded: dict[str, Recorded]
    wall_s: float
    analysed: Callable[[str, MethodChoice], Analysis]


@pytest.fixture(scope="session")
def bench(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Bench]:
    """Record every unit once per session, each the unit its serial derives (with its
    own concealed effects), as the simulated bench would mount it."""
    recordings = tmp_path_factory.mktemp("accuracy")
    recorded: dict[str, Recorded] = {}
    schedule = calibration_schedule(PLAN)
    started = time.perf_counter()
    for unit in UNITS:
        params = derive_unit(unit.serial, load=unit.load, noise_density_ug=unit.noise_ug)
        out = recordings / unit.label
        record_in_process(out, params, schedule, seed=unit.seed, loss=LOSS,
                          sync_period_s=SYNC_PERIOD_S)
        effects = tuple(sorted(e.value for e in params.effects))
        recorded[unit.label] = Recorded(unit, out, operating_optimum(params), effects)
    wall_s = time.perf_counter() - started

    @cache
    def analysed(label: str, method: MethodChoice) -> Analysis:
        return analyze(read_recording(recorded[label].recording), AnalysisOptions(method=method))

    yield Bench(recorded, wall_s, analysed)
    _print_summary(recorded, wall_s, analysed)


def _errors(estimate: Trims, optimum: Trims) -> tuple[float, float, float, float]:
    return (
        estimate.offset_a_mA - optimum.offset_a_mA,
        estimate.offset_b_mA - optimum.offset_b_mA,
        estimate.gain_a - optimum.gain_a,
        estimate.gain_b - optimum.gain_b,
    )


def _print_summary(
    recorded: dict[str, Recorded], wall_s: float, analysed: Callable[[str, MethodChoice], Analysis]
) -> None:
    """The table an engineer reads (``pytest -s``): errors per unit, worst per load."""
    lines = [
        "",
        f"acceptance recordings: {len(recorded)} units recorded in {wall_s:.1f} s",
        f"{'unit':<22}{'noise':>6} {'method':<9}{'dA mA':>7}{'dB mA':>7}{'dGa':>7}{'dGb':>7}"
        f"{'σA':>6}{'σG':>6}  effects",
    ]
    worst: dict[tuple[LoadKind, Method], np.ndarray] = {}
    for label, rec in recorded.items():
        for choice in (MethodChoice.AUTO, MethodChoice.PAPER):
            try:
                est = analysed(label, choice).estimate
            except Exception as exc:  # the summary must show what the tests already report
                lines.append(f"{label:<22}{choice.value:<9} failed: {exc}")
                continue
            err = np.array(_errors(est.trims, rec.optimum))
            key = (rec.unit.load, est.method)
            worst[key] = np.maximum(worst.get(key, np.zeros(4)), np.abs(err))
            lines.append(
                f"{label:<22}{rec.unit.noise_ug:>6.0f} {est.method.value:<9}"
                + "".join(f"{e:>7.1f}" for e in err)
                + f"{est.sigma.offset_a_mA:>6.1f}{est.sigma.gain_a:>6.1f}  "
                + ",".join(rec.effects)
            )
    lines.append("max |error| per load and method (offset A, offset B mA; gain A, gain B):")
    for (load, method), err in sorted(worst.items()):
        lines.append(f"  {load.value:<5} {method.value:<9}" + "".join(f"{e:>7.1f}" for e in err))
    print("\n".join(lines))


@pytest.mark.parametrize("unit", UNITS, ids=[u.label for u in UNITS])
def test_default_method_finds_the_optimal_trims(bench: Bench, unit: Unit) -> None:
    rec = bench.recorded[unit.label]
    analysis = bench.analysed(unit.label, MethodChoice.AUTO)
    assert analysis.estimate.method is Method.COHERENT
    d_a, d_b, d_ga, d_gb = _errors(analysis.estimate.trims, rec.optimum)
    assert abs(d_a) <= OFFSET_TOLERANCE_mA and abs(d_b) <= OFFSET_TOLERANCE_mA, (
        d_a, d_b, rec.effects
    )
    gain_tolerance = (
        DRIFT_GAIN_TOLERANCE if "sensor_clock_drift" in rec.effects else GAIN_TOLERANCE
    )
    assert abs(d_ga) <= gain_tolerance and abs(d_gb) <= gain_tolerance, (d_ga, d_gb, rec.effects)
    # Every steady hold of the schedule is a trim point (baseline plus 3 sweeps of 11),
    # except a few the 1 % of lost frames leave unsettled: these units use 30 to 34. (On
    # the virtual bus, whose frame order varies, SN3101 used 29 to 33 in nine runs.)
    assert 1 + 3 * 11 - 6 <= analysis.segments_used <= 1 + 3 * 11


@pytest.mark.parametrize("unit", UNITS, ids=[u.label for u in UNITS])
def test_paper_method_finds_the_offsets_and_warns_about_its_gain_split(
    bench: Bench, unit: Unit
) -> None:
    """The open-loop schedule sweeps the gain split at offsets 0, not at their optimum
    as the paper does, so the paper's split is biased and must say so."""
    rec = bench.recorded[unit.label]
    estimate = bench.analysed(unit.label, MethodChoice.PAPER).estimate
    assert estimate.method is Method.PAPER
    d_a, d_b, _, _ = _errors(estimate.trims, rec.optimum)
    # Magnitudes alone carry less information than phasors: on a light belt the paper's
    # offsets are noise-limited, so they must be within 3 mA or within their own 3 σ.
    sigma = estimate.sigma
    assert abs(d_a) <= max(OFFSET_TOLERANCE_mA, 3 * sigma.offset_a_mA), (d_a, sigma, rec.effects)
    assert abs(d_b) <= max(OFFSET_TOLERANCE_mA, 3 * sigma.offset_b_mA), (d_b, sigma, rec.effects)
    assert any(w.startswith("gain_split: swept with the offsets at (0, 0) mA") for w in
               estimate.warnings), estimate.warnings
