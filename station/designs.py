"""Where to measure: the trim points of each calibration phase, as pure functions.

Two designs. The paper's (section 3.1) sweeps one trim at a time across a
wide range, closed loop: offset A with B at zero, then B with A at its
estimate, then the gain split with both offsets at theirs, so each parabola
is fitted where the other trims are already right. The phase-coherent
estimator needs no sweep through the minimum, only points that make the
complex harmonic maps well determined: a star (±step on each trim axis)
around the latest estimate, round after round with smaller steps, so the
last round sits where the response is linear and the lever arm is still
large against the noise.
"""

from __future__ import annotations

import math
from dataclasses import replace

from station.analysis.estimate import TrimAxis
from station.core import GAIN_LIMITS, GAIN_UNITY, Trims, offset_limit_mA
from station.schedules import Hold, Phase, linspace_int


def within_drive_range(trims: Trims, rated_current_mA: int) -> Trims:
    """Trims clipped to what the drive accepts, rounded as the drive stores them.

    A design centred near a range edge would otherwise ask for a value the
    drive refuses with an SDO abort halfway through a run.
    """
    limit = offset_limit_mA(rated_current_mA)
    low, high = GAIN_LIMITS
    t = trims.rounded()
    return Trims(
        min(max(t.offset_a_mA, -limit), limit),
        min(max(t.offset_b_mA, -limit), limit),
        min(max(t.gain_a, low), high),
        min(max(t.gain_b, low), high),
    )


def with_split(trims: Trims, split: float) -> Trims:
    """Gains A/B moved apart by ``split`` each way, keeping their sum (the paper's step 3)."""
    centre = (trims.gain_a + trims.gain_b) / 2.0
    return replace(trims, gain_a=centre + split, gain_b=centre - split)


def star(centre: Trims, offset_step_mA: int, gain_step: int, rated_current_mA: int) -> list[Trims]:
    """The centre and ±step along offset A, offset B and the gain split, within the drive's range.

    Points that clipping merges with another (a centre at the range edge) are
    measured once: a repeated point adds time, not information.
    """
    candidates = [
        centre,
        replace(centre, offset_a_mA=centre.offset_a_mA + offset_step_mA),
        replace(centre, offset_a_mA=centre.offset_a_mA - offset_step_mA),
        replace(centre, offset_b_mA=centre.offset_b_mA + offset_step_mA),
        replace(centre, offset_b_mA=centre.offset_b_mA - offset_step_mA),
        with_split(centre, (centre.gain_a - centre.gain_b) / 2.0 + gain_step),
        with_split(centre, (centre.gain_a - centre.gain_b) / 2.0 - gain_step),
    ]
    points: list[Trims] = []
    for candidate in candidates:
        point = within_drive_range(candidate, rated_current_mA)
        if point not in points:
            points.append(point)
    return points


def offset_a_sweep(minimum_mA: int, maximum_mA: int, points: int) -> list[Trims]:
    """The paper's step (1): offset A swept, offset B and the gains nominal."""
    return [Trims(offset_a_mA=float(a)) for a in linspace_int(minimum_mA, maximum_mA, points)]


def offset_b_sweep(offset_a_mA: float, minimum_mA: int, maximum_mA: int,
                   points: int) -> list[Trims]:
    """The paper's step (2): offset B swept with A at its estimate (whole mA, as stored)."""
    a = float(round(offset_a_mA))
    return [Trims(a, float(b)) for b in linspace_int(minimum_mA, maximum_mA, points)]


def gain_sweep(offset_a_mA: float, offset_b_mA: float, minimum: int, maximum: int,
               points: int) -> list[Trims]:
    """The paper's step (3): gain A swept, gain B = 2·unity − gain A, offsets at their estimates."""
    a, b = float(round(offset_a_mA)), float(round(offset_b_mA))
    return [
        Trims(a, b, float(g), float(2 * GAIN_UNITY - g))
        for g in linspace_int(minimum, maximum, points)
    ]


def samples_per_period(electrical_hz: float, sync_period_s: float) -> float:
    return 1.0 / (electrical_hz * sync_period_s)


def hold_cycles(periods: float, electrical_hz: float, sync_period_s: float) -> int:
    """SYNC cycles covering ``periods`` electrical periods (rounded up: never fewer)."""
    return max(1, math.ceil(periods * samples_per_period(electrical_hz, sync_period_s) - 1e-9))


def holds_for(
    points: list[Trims],
    *,
    phase: Phase,
    velocity: int,
    amplitude_mA: int,
    hold_periods: float,
    electrical_hz: float,
    sync_period_s: float,
    lead_periods: float = 0.0,
) -> tuple[Hold, ...]:
    """One hold per point; the first one longer by ``lead_periods`` (a spin-up from rest)."""
    cycles = hold_cycles(hold_periods, electrical_hz, sync_period_s)
    lead = hold_cycles(lead_periods, electrical_hz, sync_period_s) if lead_periods > 0 else 0
    return tuple(
        Hold(phase, velocity, amplitude_mA, point, cycles + (lead if i == 0 else 0))
        for i, point in enumerate(points)
    )


def axis_sweep(centre: Trims, axis: TrimAxis, span: int, points: int,
               rated_current_mA: int) -> list[Trims]:
    """``points`` trims over centre ± span along one axis, the others held (the paper's
    sweep, re-centred): within the drive's range, merged points measured once."""
    out: list[Trims] = []
    if axis is TrimAxis.GAIN_SPLIT:
        split = (centre.gain_a - centre.gain_b) / 2.0
        candidates = [with_split(centre, split + s) for s in linspace_int(-span, span, points)]
    elif axis is TrimAxis.OFFSET_A:
        candidates = [replace(centre, offset_a_mA=centre.offset_a_mA + s)
                      for s in linspace_int(-span, span, points)]
    else:
        candidates = [replace(centre, offset_b_mA=centre.offset_b_mA + s)
                      for s in linspace_int(-span, span, points)]
    for candidate in candidates:
        point = within_drive_range(candidate, rated_current_mA)
        if point not in out:
            out.append(point)
    return out
