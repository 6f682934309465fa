"""The run's sensor clock as its phasors see it, for the phase-coherent estimate.

A hold times the sensor's clock from its own waveform (``station.analysis.
sampling``); this module times it from what the clock does to a whole run: it
turns every hold's phasors by k·dθ/dn per sample of delay, in proportion to
the hold's time and |H|, which no trim explains. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from station.analysis.estimate import phasor_misfit, phasor_terms
from station.analysis.pipeline import Measured
from station.analysis.sampling import POOL_SIGMAS, ClockPhase, RateObservation

_REFINE_SIGMAS = 4.0
"""How far (in the holds' standard errors) the phasors may move a clock the holds timed;
one they could not tell from zero is looked for within ``POOL_SIGMAS`` of their median."""
_PHASORS_SEE = 40.0
"""How much a clock the holds could not time must take out of the phasors' misfit, in
units of what is left per degree of freedom, to be kept: five standard errors of its two
parameters (rate and the lattice's place) after the ~200 pairs the search tries, which
is how often chance alone would find that much somewhere (a belt without any clock but
with an eccentric rotor took 29 from a 406 ppm clock that is not there: seed
1728856850)."""
CLOCK_RANGE = 1000e-6
"""The largest clock offset looked for (u per sample) where the holds' own timing is too
loose to bound it: a sensor's crystal is specified to ±100 ppm or so; an internal RC
oscillator may be off by far more, but then the holds see it."""
_RATES = (25, 9, 9)
"""Rates tried per pass: across the whole range, then one step of the pass before
either side of its best."""
_PHASES = (8, 5, 3)
"""Places of the wrap lattice tried per rate where no hold placed a wrap: 8 across one
lattice period, then across one step of the pass before either side of its best."""


def search_range(clock: RateObservation) -> tuple[float, float]:
    """The rates the phasors may choose from: within ``_REFINE_SIGMAS`` of a clock the
    holds timed, wherever it lies (an RC oscillator may be off by percent); one they could
    not tell from zero within ``POOL_SIGMAS`` of their median, inside ``CLOCK_RANGE``.
    The clamp is for the second only: applied to a clock of −21,000 ppm the holds timed,
    it turned the range inside out and the search chose −3,083 ppm."""
    if clock.clear_of_zero:
        reach = _REFINE_SIGMAS * clock.sigma
        return clock.rate - reach, clock.rate + reach
    reach = POOL_SIGMAS * clock.sigma
    return max(clock.rate - reach, -CLOCK_RANGE), min(clock.rate + reach, CLOCK_RANGE)


def clock_from_phasors(held: Sequence[Measured], clock: RateObservation,
                       wraps: Sequence[int]) -> ClockPhase:
    """The run's clock as the phasors see it: near the holds' own (``clock``), the rate
    and the places of its wraps at which every hold's H1 and H2 fit their affine maps best.

    A hold times the clock from how its samples drift along its own waveform, to about
    50 ppm in 0.2 s; pooled over a run's 19 holds that is 15 ppm, and across the run's
    six seconds 15 ppm turns H2 by 1.3°: 25 noise σ on the first round's widest points
    (seed 1201662595: −166 ppm timed for −140). A hold still ringing after its step is not
    timed at all, and on belt units the holds could not tell ±400 ppm from zero (seed
    1053173331). The phasors time it far better, because a clock the trims cannot
    explain turns a run's points in proportion to their time and their |H|, and a wrap
    turns every later point by a whole sample. Wraps placed by the holds fix the lattice;
    without one, its place is searched too. A grid, not a descent: as the rate or the
    lattice moves, a wrap crosses a hold and the misfit jumps.
    """
    if not math.isfinite(clock.sigma) or clock.sigma <= 0.0:
        return ClockPhase(0.0, None)
    seen = clock.clear_of_zero

    # The maps' terms are chosen once, on the holds' own clock, and kept for every rate
    # tried: a term that came and went with the rate would move the misfit by more than
    # the clock does.
    terms = phasor_terms([m.point(ClockPhase.of(clock.rate if seen else 0.0, wraps))
                          for m in held])
    if terms is None:
        return ClockPhase.of(clock.rate if seen else 0.0, wraps)

    def misfit(phase: ClockPhase) -> tuple[float, int]:
        return phasor_misfit([m.point(phase) for m in held], terms)

    def candidates(rate: float, around: float | None, width: float, count: int
                   ) -> list[ClockPhase]:
        if rate == 0.0 or wraps:
            return [ClockPhase.of(rate, wraps)]
        period = 1.0 / abs(rate)
        if around is None:
            return [ClockPhase(rate, k * period / count) for k in range(count)]
        return [ClockPhase(rate, float(a)) for a in
                np.linspace(around - width * period, around + width * period, count)]

    def score(entry: tuple[ClockPhase, tuple[float, int]], scale: float) -> float:
        # The phasors' misfit in units of what is left per degree of freedom (physics the
        # maps leave out turns phasors too: a belt's transients, an eccentric rotor),
        # beside what the holds' own timing says.
        phase, (chi2, _) = entry
        return chi2 / scale + ((phase.rate - clock.rate) / clock.sigma) ** 2

    tried: list[tuple[ClockPhase, tuple[float, int]]] = []
    low, high = search_range(clock)
    width, anchor, scale = 0.5, None, 1.0
    best = ClockPhase.of(clock.rate, wraps)
    for fine, (rates, phases) in enumerate(zip(_RATES, _PHASES, strict=True)):
        grid = np.linspace(low, high, rates)
        tried.extend((phase, misfit(phase)) for rate in grid
                     for phase in candidates(float(rate), anchor, width, phases))
        least = min(tried, key=lambda e: e[1][0])
        if not math.isfinite(least[1][0]):
            return ClockPhase.of(clock.rate if seen else 0.0, wraps)
        scale = max(1.0, least[1][0] / max(least[1][1], 1))
        best = min(tried, key=lambda e: score(e, scale))[0]
        step = float(grid[1] - grid[0])
        low, high, anchor = best.rate - step, best.rate + step, best.anchor
        width = width * 2.0 / phases if fine else 1.0 / phases
    if not seen and (misfit(ClockPhase(0.0, None))[0] - misfit(best)[0]) / scale < _PHASORS_SEE:
        return ClockPhase(0.0, None)
    return best
