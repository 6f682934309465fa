"""Motion schedules: what the drive is told to do, hold by hold.

A schedule is data (a tuple of holds), so the same runner drives a simulated
bench or a real one, and a recording can name the schedule it followed. Every
hold lasts a whole number of electrical periods at its speed, because the
demodulation downstream integrates over whole periods.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, replace
from enum import StrEnum
from typing import Final

import numpy as np

from station.core import GAIN_UNITY, NOMINAL_TRIMS, SENSOR_RANGES_G, Trims


class ScheduleName(StrEnum):
    """Schedules that ``station sim record`` knows by name (CLI.md)."""

    CALIBRATION = "calibration"
    CHARACTERIZATION = "characterization"


class Phase(StrEnum):
    """What a hold is for; recorded as a label so people can read a run back."""

    STANDSTILL = "standstill"
    BASELINE = "baseline"
    SWEEP_OFFSET_A = "sweep_offset_a"
    SWEEP_OFFSET_B = "sweep_offset_b"
    SWEEP_GAIN = "sweep_gain"
    CONDITION = "condition"
    STEP_OFFSET_A = "step_offset_a"
    STEP_OFFSET_B = "step_offset_b"
    STEP_GAIN = "step_gain"
    SWEEP_STAR = "sweep_star"
    VERIFY = "verify"
    STOP = "stop"


@dataclass(frozen=True)
class Hold:
    """Hold velocity, amplitude and trims for ``cycles`` SYNC periods."""

    phase: Phase
    velocity: int
    amplitude_mA: int
    trims: Trims
    cycles: int


@dataclass(frozen=True)
class Schedule:
    """Holds in order, with the microstep resolution their velocities assume and
    the sensor range the run needs (extreme trims shake a light load hard)."""

    name: str
    holds: tuple[Hold, ...]
    microsteps: int = 256
    sensor_range_g: int = 2

    def __post_init__(self) -> None:
        if self.sensor_range_g not in SENSOR_RANGES_G:
            raise ValueError(
                f"sensor range {self.sensor_range_g} g is not one of {SENSOR_RANGES_G}"
            )

    @property
    def cycles(self) -> int:
        return sum(h.cycles for h in self.holds)


def velocity_for(electrical_hz: float, microsteps: int) -> int:
    """Microsteps/s for an electrical frequency: one electrical period is 4 full steps."""
    return round(electrical_hz * 4 * microsteps)


def cycles_for(seconds: float, electrical_hz: float, sync_period_s: float) -> int:
    """SYNC cycles covering at least ``seconds`` and a whole number of electrical periods."""
    if electrical_hz == 0:
        return max(1, round(seconds / sync_period_s))
    period = 1.0 / abs(electrical_hz)
    periods = max(1, math.ceil(seconds / period - 1e-9))
    return max(1, round(periods * period / sync_period_s))


def linspace_int(start: int, stop: int, points: int) -> list[int]:
    """Evenly spaced integers from start to stop (the drive takes whole mA and 1/10000)."""
    if points == 1:
        return [round((start + stop) / 2)]
    return [round(start + (stop - start) * i / (points - 1)) for i in range(points)]


@dataclass(frozen=True)
class SweepPlan:
    """The paper's calibration experiment, parameterised (section 3.1)."""

    electrical_hz: float = 20.0
    amplitude_mA: int = 1000
    offset_span_mA: int = 500
    offset_points: int = 11
    gain_low: int = 7000
    gain_high: int = 13000
    gain_points: int = 11
    dwell_s: float = 1.0
    standstill_s: float = 0.3
    # Peaks at the sweep's ends reach 6-18 g on a light disk (the distorted
    # torque excites the rotor's mode); 8 g keeps most holds unclipped.
    sensor_range_g: int = 8


def calibration_schedule(
    plan: SweepPlan, *, microsteps: int = 256, sync_period_s: float = 0.001
) -> Schedule:
    """Standstill, baseline, offset A sweep, offset B sweep, gain split sweep, stop.

    The sweeps are open loop (phase B held at its nominal trim while A is
    swept, and so on), so a recording's content does not depend on any online
    estimate; the paper's eq. (16) makes the two offsets act on orthogonal
    phasors, so the A sweep's minimum does not depend on B's value.
    """
    v = velocity_for(plan.electrical_hz, microsteps)
    dwell = cycles_for(plan.dwell_s, plan.electrical_hz, sync_period_s)
    still = cycles_for(plan.standstill_s, 0.0, sync_period_s)
    amp = plan.amplitude_mA
    holds: list[Hold] = [
        Hold(Phase.STANDSTILL, 0, amp, NOMINAL_TRIMS, still),
        Hold(Phase.BASELINE, v, amp, NOMINAL_TRIMS, dwell),
    ]
    offsets = linspace_int(-plan.offset_span_mA, plan.offset_span_mA, plan.offset_points)
    for phase, field in (
        (Phase.SWEEP_OFFSET_A, "offset_a_mA"),
        (Phase.SWEEP_OFFSET_B, "offset_b_mA"),
    ):
        holds.extend(
            Hold(phase, v, amp, replace(NOMINAL_TRIMS, **{field: offset}), dwell)
            for offset in offsets
        )
    for gain_a in linspace_int(plan.gain_low, plan.gain_high, plan.gain_points):
        trims = replace(NOMINAL_TRIMS, gain_a=gain_a, gain_b=2 * GAIN_UNITY - gain_a)
        holds.append(Hold(Phase.SWEEP_GAIN, v, amp, trims, dwell))
    holds.append(Hold(Phase.STOP, 0, amp, NOMINAL_TRIMS, still))
    return Schedule(ScheduleName.CALIBRATION.value, tuple(holds), microsteps, plan.sensor_range_g)


@dataclass(frozen=True)
class CharacterizationPlan:
    """Conditions that make the effects separable (issue: diagnose).

    Several speeds in both directions tell order-locked effects from
    fixed-frequency ones and show direction dependence; three currents show
    how each term scales with I; small trim steps at every condition let the
    trims be re-estimated per condition (drift of "constant" parameters).
    """

    electrical_hz: Sequence[float] = (10.0, 20.0, 35.0)
    amplitudes_mA: Sequence[int] = (600, 800, 1000)
    offset_step_mA: int = 40
    gain_step: int = 400
    settle_s: float = 0.8
    step_s: float = 0.5
    min_periods: int = 10
    """Every hold lasts at least this many electrical periods: the segmenter needs six
    to judge the rotor settled, and a phasor a few more after that."""
    standstill_s: float = 0.3
    # Untrimmed units near the rotor's resonance swing to 30-40 m/s² at some orders;
    # at 8 g the LSB (2.4 mm/s²) is still far below the sensor's own noise.
    sensor_range_g: int = 8


def characterization_schedule(
    plan: CharacterizationPlan,
    *,
    microsteps: int = 256,
    sync_period_s: float = 0.001,
    center: Trims = NOMINAL_TRIMS,
) -> Schedule:
    """Both directions, every speed and current, small trim steps around ``center``.

    A station characterizes a unit around the trims it already has (near its
    optimum once calibrated), so the rotor swings little and the effects are
    not buried under the offsets' own ripple; the run ends on ``center`` again.
    """
    still = cycles_for(plan.standstill_s, 0.0, sync_period_s)
    top = max(plan.amplitudes_mA)
    c = center
    holds: list[Hold] = [Hold(Phase.STANDSTILL, 0, top, c, still)]
    for direction in (1, -1):
        for hz in plan.electrical_hz:
            v = direction * velocity_for(hz, microsteps)
            shortest = plan.min_periods / hz
            settle = cycles_for(max(plan.settle_s, shortest), hz, sync_period_s)
            step = cycles_for(max(plan.step_s, shortest), hz, sync_period_s)
            for amp in plan.amplitudes_mA:
                steps = (
                    (Phase.STEP_OFFSET_A,
                     replace(c, offset_a_mA=c.offset_a_mA + plan.offset_step_mA)),
                    (Phase.STEP_OFFSET_B,
                     replace(c, offset_b_mA=c.offset_b_mA + plan.offset_step_mA)),
                    (Phase.STEP_GAIN,
                     replace(c, gain_a=c.gain_a + plan.gain_step,
                             gain_b=c.gain_b - plan.gain_step)),
                )
                holds.append(Hold(Phase.CONDITION, v, amp, c, settle))
                holds.extend(Hold(phase, v, amp, trims, step) for phase, trims in steps)
    holds.append(Hold(Phase.STOP, 0, top, c, still))
    return Schedule(
        ScheduleName.CHARACTERIZATION.value, tuple(holds), microsteps, plan.sensor_range_g
    )


@dataclass(frozen=True)
class RandomCharacterizationRanges:
    """What ``random_characterization`` draws from: a characterization as someone else
    might write it, within what the diagnosis is meant to cope with."""

    speeds: tuple[int, int] = (2, 6)
    electrical_hz: tuple[float, float] = (5.0, 40.0)
    amplitudes: tuple[int, int] = (2, 4)
    lowest_amplitude_mA: int = 300
    strong_share: float = 0.8
    """At least one amplitude is at least this share of the rated current: the effects that
    grow with I must show somewhere."""
    hold_s: tuple[float, float] = (0.4, 1.0)
    offset_step_mA: tuple[int, int] = (20, 80)
    gain_step: tuple[int, int] = (200, 800)
    both_signs_probability: float = 0.5
    sensor_ranges_g: tuple[int, ...] = (4, 8, 16)


RANDOM_CHARACTERIZATION: Final = RandomCharacterizationRanges()
RANDOM_CHARACTERIZATION_NAME: Final = f"{ScheduleName.CHARACTERIZATION.value}-random"
"""Recorded as the schedule's name, so a random draw is never taken for the station's own."""

HZ_RESOLUTION = 0.5
"""People write speeds in round figures; a 0.5 Hz grid still gives 71 choices."""
_AMPLITUDE_RESOLUTION_MA = 10


def random_characterization(
    rng: np.random.Generator,
    *,
    microsteps: int = 256,
    sync_period_s: float = 0.001,
    rated_current_mA: int = 1000,
    center: Trims = NOMINAL_TRIMS,
    ranges: RandomCharacterizationRanges = RANDOM_CHARACTERIZATION,
) -> Schedule:
    """A characterization drawn at random, for benchmarking the diagnosis beyond the
    one schedule the station itself runs.

    The station's own plan lets every hold settle for whole periods and at least ten
    of them; a characterization written elsewhere need not, so here every hold
    (standstill and stop included) lasts the same number of SYNC cycles whatever its
    speed: a 0.5 s hold at 6 Hz is 3 periods, at 7 Hz 3.5. Speeds, directions and
    currents come in a drawn order, as a person might list them; at each condition the
    hold on ``center`` comes first, then the steps (offset A, offset B, gain split,
    each positive; with both signs, the negative ones follow).
    """
    r = ranges
    if rated_current_mA < r.lowest_amplitude_mA:
        raise ValueError(
            f"rated current {rated_current_mA} mA is below the lowest amplitude drawn "
            f"({r.lowest_amplitude_mA} mA)"
        )
    hz_grid = np.arange(
        math.ceil(r.electrical_hz[0] / HZ_RESOLUTION),
        math.floor(r.electrical_hz[1] / HZ_RESOLUTION) + 1,
    ) * HZ_RESOLUTION
    n_speeds = int(rng.integers(r.speeds[0], r.speeds[1] + 1))
    speeds = [float(hz) for hz in rng.choice(hz_grid, size=n_speeds, replace=False)]
    amplitudes = _draw_amplitudes(rng, rated_current_mA, r)
    hold_s = float(rng.uniform(*r.hold_s))
    cycles = max(1, round(hold_s / sync_period_s))
    offset_step = int(rng.integers(r.offset_step_mA[0], r.offset_step_mA[1] + 1))
    gain_step = int(rng.integers(r.gain_step[0], r.gain_step[1] + 1))
    signs = (1, -1) if rng.random() < r.both_signs_probability else (1,)
    directions = (1, -1) if rng.random() < 0.5 else (-1, 1)
    direction_outer = bool(rng.random() < 0.5)
    range_g = int(rng.choice(r.sensor_ranges_g))

    c = center
    steps: list[tuple[Phase, Trims]] = []
    for sign in signs:
        steps += [
            (Phase.STEP_OFFSET_A, replace(c, offset_a_mA=c.offset_a_mA + sign * offset_step)),
            (Phase.STEP_OFFSET_B, replace(c, offset_b_mA=c.offset_b_mA + sign * offset_step)),
            (Phase.STEP_GAIN, replace(c, gain_a=c.gain_a + sign * gain_step,
                                      gain_b=c.gain_b - sign * gain_step)),
        ]
    conditions = (
        [(d, hz) for d in directions for hz in speeds]
        if direction_outer
        else [(d, hz) for hz in speeds for d in directions]
    )
    top = max(amplitudes)
    holds: list[Hold] = [Hold(Phase.STANDSTILL, 0, top, c, cycles)]
    for direction, hz in conditions:
        v = direction * velocity_for(hz, microsteps)
        for amp in amplitudes:
            holds.append(Hold(Phase.CONDITION, v, amp, c, cycles))
            holds.extend(Hold(phase, v, amp, trims, cycles) for phase, trims in steps)
    holds.append(Hold(Phase.STOP, 0, top, c, cycles))
    return Schedule(RANDOM_CHARACTERIZATION_NAME, tuple(holds), microsteps, range_g)


def _draw_amplitudes(
    rng: np.random.Generator, rated_current_mA: int, r: RandomCharacterizationRanges
) -> list[int]:
    """Distinct whole-10 mA currents, one of them strong, in a drawn order."""
    step = _AMPLITUDE_RESOLUTION_MA
    grid = np.arange(math.ceil(r.lowest_amplitude_mA / step), rated_current_mA // step + 1) * step
    strong = grid[grid >= r.strong_share * rated_current_mA]
    if strong.size == 0:  # a rating that is no multiple of 10 mA: its own value is strong
        grid = np.append(grid, rated_current_mA)
        strong = grid[-1:]
    wanted = min(int(rng.integers(r.amplitudes[0], r.amplitudes[1] + 1)), grid.size)
    first = int(rng.choice(strong))
    others = rng.choice(grid[grid != first], size=wanted - 1, replace=False)
    amplitudes = [first, *(int(a) for a in others)]
    return [amplitudes[i] for i in rng.permutation(len(amplitudes))]


def named_schedule(
    name: ScheduleName, *, microsteps: int = 256, sync_period_s: float = 0.001
) -> Schedule:
    if name is ScheduleName.CALIBRATION:
        return calibration_schedule(SweepPlan(), microsteps=microsteps, sync_period_s=sync_period_s)
    return characterization_schedule(
        CharacterizationPlan(), microsteps=microsteps, sync_period_s=sync_period_s
    )
