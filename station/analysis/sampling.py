"""The sensor's own sample instants, where its clock runs apart from SYNC.

ICD.md §5 puts sample n at n·T. A sensor that samples on its own clock, off by
δ, reports at SYNC n what it sampled u_n periods earlier or later, and u_n moves
by δ per sample until the sensor skips a sample (a faster clock: u jumps by +1)
or repeats one (slower: −1). Within a hold at constant trims the waveform is
periodic in the electrical angle, so a late sample reads the waveform at
θ_n + u_n·dθ/dn: a steady ramp of u turns order k by k·dθ/dn·δ per sample, and
a wrap shifts every later sample of the hold by a whole sample. On a unit whose
detent or flux harmonics put tens of m/s² into orders 4-12, one skipped sample
in a hold leaked into orders 1 and 2 as much as the trims' own ripple near the
null (seed 5020: a 0.15 m/s² H1 read as 1.16 m/s²), and the ramp alone left
the residual at three times the noise.

So the harmonics are fitted at the samples' own instants: this module measures
each hold's ramp (``observe_rate``), pools the holds' rates into the clock
(``pooled_rate``: a clock turns every hold alike, a transient one hold its own
way), finds a wrap in a hold by the whole-sample step it makes
(``sample_delays``), and gives each sample its delay for the demodulation.
Within a hold the delays alone would be centred on the hold, leaving each
phasor turned by wherever u stood at the hold's mean instant: from one hold
to the next a −140 ppm clock turned H2 by up to 14° over a run, and the
estimate's last round of points near the null fitted its affine maps at
twice the noise (seed 1201662595). ``ClockPhase`` places every hold on the
run's one clock instead: u = δ·n plus the wraps so far, counted on the
lattice of wraps the holds placed (one every 1/|δ| samples), so that every
phasor of a run shares one reference. Pure numpy.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Final

import numpy as np
from numpy.typing import NDArray

from station.analysis.harmonics import _design, _nyquist

WRAP_EXPLAINS: Final = 50.0
"""Noise variances (of one sample) a whole-sample step must take out of a hold's residual
to be taken as a wrap. A wrap on a waveform with strong detent orders takes out thousands
(seed 5020: the residual's σ from 9.0 to 0.11 m/s²); a hold that merely rings gains a few
from any step, which at this bar is never one."""
_EDGE: Final = 3
"""Samples at either end of a hold where a step is not looked for: there it is a constant
delay, which the phasors take up."""
_RAMP_ITERATIONS: Final = 3
"""Gauss-Newton passes for a hold's rate: the delay's effect is linearised about the
latest one, and at the highest fitted orders a few tenths of a sample is not linear."""
TIMED_ORDERS: Final = 16
"""Orders whose turn times the samples. Every order the sampling resolves is fitted (on a
rough unit, orders 17-24 left out of the fit pulled a 254 ppm clock to 2 ppm: seed 9336),
but above this one a tone may be an alias of an order beyond the Nyquist rate, which a
delay turns the other way: timed as what it seems, such tones pulled the same clock to 0.
At 20 Hz, order 16 is 320 Hz, below the sensor's band edge (ICD.md §3: at least 40 % of
the SYNC rate), beyond which an order would have to lie to alias onto it."""
MIN_RATE_SAMPLES: Final = 64
"""Fewer present samples than this are not timed."""


@dataclass(frozen=True)
class RateObservation:
    """One hold's own clock rate: u's change per sample, and its standard error
    (infinite where the hold's waveform is too weak or short to time it)."""

    rate: float
    sigma: float

    @property
    def clear_of_zero(self) -> bool:
        """Whether the rate stands ``POOL_SIGMAS`` standard errors clear of zero: a clock."""
        return abs(self.rate) > POOL_SIGMAS * self.sigma


@dataclass(frozen=True)
class Delays:
    """Each present sample's delay (in sample periods, centred on the hold) and where a
    wrap was found (the hold's first sample after it, None without one)."""

    delays: NDArray[np.float64]  # (n,) 0 where the sample is missing
    wrap_at: int | None


@dataclass(frozen=True)
class _Present:
    """A hold's present samples, their SYNC angles and positions, and the orders fitted:
    every order the sampling resolves (a rough unit's orders 17-24, left out, pulled a
    254 ppm clock to 2 ppm: seed 9336)."""

    y: NDArray[np.float64]
    angle: NDArray[np.float64]
    index: NDArray[np.float64]  # position in the hold
    step: float  # dθ/dn
    orders: int

    @classmethod
    def of(cls, window: NDArray[np.float64], angle: NDArray[np.float64],
           samples_per_period: float) -> _Present | None:
        """None where the hold cannot be timed: too few samples for its orders."""
        present = ~np.isnan(window)
        orders = _nyquist(samples_per_period)
        if angle.size < 2 or int(present.sum()) < max(MIN_RATE_SAMPLES, 4 * orders + 4):
            return None
        return cls(window[present], angle[present],
                   np.flatnonzero(present).astype(np.float64), float(angle[1] - angle[0]),
                   orders)

    @property
    def centred(self) -> NDArray[np.float64]:
        out: NDArray[np.float64] = self.index - self.index.mean()
        return out

    def fit(self, delays: NDArray[np.float64]
            ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """The harmonics' coefficients and residual with each sample ``delays`` late."""
        design = _design(self.angle + self.step * delays, self.orders)
        solution = np.linalg.lstsq(design, self.y, rcond=None)
        coef: NDArray[np.float64] = np.asarray(solution[0], dtype=np.float64)
        residual: NDArray[np.float64] = self.y - design @ coef
        return coef, residual

    def slope(self, coef: NDArray[np.float64], delays: NDArray[np.float64]
              ) -> NDArray[np.float64]:
        """How the fitted waveform's timed orders (``TIMED_ORDERS``) move per sample of
        delay at each sample."""
        timed = min(self.orders, TIMED_ORDERS)
        k = np.arange(1, timed + 1, dtype=np.float64)
        phase = np.outer(self.angle + self.step * delays, k)
        cos_part = coef[1:timed + 1]
        sin_part = coef[self.orders + 1:self.orders + 1 + timed]
        out: NDArray[np.float64] = self.step * ((np.cos(phase) * k) @ sin_part
                                                - (np.sin(phase) * k) @ cos_part)
        return out

    def wrap(self, ramp: NDArray[np.float64], signs: tuple[float, ...]
             ) -> NDArray[np.float64] | None:
        """The step a wrap adds to ``ramp``, or None: located to first order
        (``_best_step``), then kept only where the exact fit at the stepped instants
        explains ``WRAP_EXPLAINS`` noise variances more (a whole sample is far from linear
        at the highest orders)."""
        coef, residual = self.fit(ramp)
        where, sign = _best_step(residual, self.slope(coef, ramp), signs)
        dof = self.y.size - (2 * self.orders + 1)
        if where < 0 or dof <= 0:
            return None
        jump = np.where(self.index >= self.index[where], sign, 0.0)
        jump -= jump.mean()
        _, stepped = self.fit(ramp + jump)
        left = float(stepped @ stepped)
        if float(residual @ residual) - left <= WRAP_EXPLAINS * left / dof:
            return None
        return jump


def _best_step(residual: NDArray[np.float64], slope: NDArray[np.float64],
               signs: tuple[float, ...]) -> tuple[int, float]:
    """Where a whole-sample step of the delay (with a free constant beside it) best
    explains ``residual`` to first order, and its sign: cumulative sums make every
    position one pass. Returns (-1, 0) when no position improves on no step."""
    n = residual.size
    ss, sr = float(slope @ slope), float(slope @ residual)
    if n <= 2 * _EDGE or ss <= 0.0:
        return -1, 0.0
    rr = float(residual @ residual)
    plain = rr - sr * sr / ss
    tail_ss = np.cumsum((slope * slope)[::-1])[::-1]
    tail_sr = np.cumsum((slope * residual)[::-1])[::-1]
    best, where, sign = 0.0, -1, 0.0
    for s in signs:
        left = (rr - 2.0 * s * tail_sr + tail_ss) - (sr - s * tail_ss) ** 2 / ss
        inner = left[_EDGE:n - _EDGE]
        m = int(np.argmin(inner))
        if plain - float(inner[m]) > best:
            best, where, sign = plain - float(inner[m]), m + _EDGE, s
    return where, sign


def observe_rate(window: NDArray[np.float64], angle: NDArray[np.float64],
                 samples_per_period: float) -> RateObservation:
    """The hold's clock rate from the way its samples drift along its own waveform.

    A wrap is looked for first (either way), so that its step does not pass for a ramp;
    then u = rate·(n − n̄) is fitted by Gauss-Newton on the linearised waveform, with a
    free constant beside it (a constant delay is a turn of the phasors, which the hold
    cannot tell from their own phase).

    Not for a hold that clipped: its samples are missing at the same phases of every
    period, where a fit of every order has no data and its slope means nothing (seed
    9336: holds with 20 % clipped claimed a 254 ppm clock was 0 ± 0.001 ppm).
    """
    hold = _Present.of(window, angle, samples_per_period)
    if hold is None:
        return RateObservation(0.0, math.inf)
    t = hold.centred
    jump = hold.wrap(np.zeros_like(t), (1.0, -1.0))
    base = np.zeros_like(t) if jump is None else jump
    rate = 0.0
    design = np.empty((t.size, 2))
    residual = hold.y
    for _ in range(_RAMP_ITERATIONS):
        delays = base + rate * t
        coef, residual = hold.fit(delays)
        slope = hold.slope(coef, delays)
        design[:, 0] = slope
        design[:, 1] = slope * t
        solution, *_ = np.linalg.lstsq(design, residual, rcond=None)
        rate += float(solution[1])
    dof = t.size - (2 * hold.orders + 1) - 2
    gram = design.T @ design
    if dof <= 0 or abs(float(np.linalg.det(gram))) <= 0.0:
        return RateObservation(0.0, math.inf)
    variance = float(residual @ residual) / dof * float(np.linalg.inv(gram)[1, 1])
    if not (math.isfinite(rate) and math.isfinite(variance) and variance > 0.0):
        return RateObservation(0.0, math.inf)
    return RateObservation(rate, math.sqrt(variance))


def sample_delays(window: NDArray[np.float64], angle: NDArray[np.float64],
                  samples_per_period: float, rate: float, *, wrap: float) -> Delays:
    """Each sample's delay under a clock of ``rate`` (u per sample), with the wrap of
    sign ``wrap`` where one falls in the hold (0: none is looked for; ``wrap_sign``)."""
    delays = np.zeros(window.size)
    present = ~np.isnan(window)
    where = np.flatnonzero(present)
    if where.size:
        delays[present] = rate * (where - where.mean())
    hold = _Present.of(window, angle, samples_per_period) if wrap != 0.0 else None
    if hold is None:
        return Delays(delays, None)
    ramp = rate * hold.centred
    jump = hold.wrap(ramp, (wrap,))
    if jump is None:
        return Delays(delays, None)
    delays[present] = ramp + jump
    first = int(np.argmax(np.abs(np.diff(jump)) > 0.5)) + 1
    return Delays(delays, int(hold.index[first]))


@dataclass(frozen=True)
class ClockPhase:
    """Where the sensor's clock stands against SYNC over a whole run, up to one constant.

    u_n = δ·n + s·W(n), s the step a wrap makes (``wrap_sign``) and W(n) the wraps
    before sample n: one every 1/|δ| samples, on the lattice through the wraps the holds
    placed (``anchor``). Without a placed wrap W is 0: a clock that wrapped where no hold
    could see it (between holds, or in holds too quiet to show the step) is then
    followed by its ramp alone, which is what the hold-centred delays did before it.
    """

    rate: float  # δ, u per sample
    anchor: float | None  # a wrap's place on the run's sample index, None without one

    @classmethod
    def of(cls, rate: float, wraps: Sequence[int]) -> ClockPhase:
        """The lattice that best fits the wraps placed (absolute indices): their circular
        mean on the lattice's period, so that one wrap placed a few samples off by a
        hold's noise does not move the others."""
        if rate == 0.0 or not wraps:
            return cls(rate, None)
        period = 1.0 / abs(rate)
        turns = np.exp(2j * math.pi * np.asarray(wraps, dtype=np.float64) / period)
        phase = float(np.angle(turns.mean())) % (2 * math.pi)
        return cls(rate, phase / (2 * math.pi) * period)

    def wraps_before(self, index: NDArray[np.float64]) -> NDArray[np.float64]:
        """W(n): the lattice's wraps at or before each sample index (0 without an anchor),
        up to a constant."""
        if self.anchor is None or self.rate == 0.0:
            return np.zeros_like(index)
        out: NDArray[np.float64] = np.floor((index - self.anchor) * abs(self.rate)) + 1.0
        return out

    def delays(self, index: NDArray[np.float64], own_wrap: int | None = None, *,
               searched: bool = False) -> NDArray[np.float64]:
        """u at each absolute sample ``index`` of one hold (in samples, up to the run's one
        constant); ``own_wrap`` the wrap the hold itself placed (its first sample after
        it), which is kept where it was found and counted as the lattice's nearest wrap.

        A hold ``searched`` for a wrap that found none has none: a wrap the lattice puts
        inside it is taken to fall just outside, at the nearer end. The lattice places
        wraps one 1/|δ| apart, so a rate known to 1 % misplaces the next wrap by tens of
        samples, and a whole-sample step put where the waveform has none leaks its
        detent orders into every other: a verification of 5 periods (seed 1268081785,
        a 214 ppm clock) read H1 0.60 m/s² with the lattice's wrap in its 117th sample
        and 0.03 without it, its residual 12.6 m/s² against 0.13.
        """
        ramp = self.rate * index
        sign = wrap_sign(self.rate)
        if own_wrap is not None and self.anchor is not None:
            nearest = round((own_wrap - self.anchor) * abs(self.rate))
            count = nearest + (index >= own_wrap).astype(np.float64)
        else:
            count = self.wraps_before(index)
            if searched and index.size and count[-1] - count[0] == 1.0:
                inside = int(np.argmax(count > count[0]))
                nearer_start = inside < index.size - inside
                count = np.full_like(count, count[-1] if nearer_start else count[0])
        out: NDArray[np.float64] = ramp + sign * count
        return out


def wrap_sign(rate: float) -> float:
    """The step a clock of ``rate`` makes when it wraps: +1 a skipped sample (faster than
    SYNC, its samples ever earlier), −1 a repeated one (slower), 0 without a clock."""
    return 0.0 if rate == 0.0 else -math.copysign(1.0, rate)


POOL_SIGMAS: Final = 5.0
"""Standard errors the pooled rate must stand clear of zero to be taken as a clock."""
MIN_POOLED: Final = 3
"""Holds that must have timed a rate before any is pooled."""
MAX_RATE: Final = 5000e-6
"""The fastest clock a hold's timing is believed for (u per sample): beyond it a hold of
200 samples would hold a wrap or more, which this model has at most one of. A ringing
hold that times such a rate timed its transient: on one draw, holds of a 137 ppm unit
pooled to −21,058 ppm."""


def pooled_rate(observations: Sequence[RateObservation]) -> float:
    """The clock the holds agree on (u per sample), or 0 unless it is clear of zero
    (``pooled_clock``)."""
    pooled = pooled_clock(observations)
    return pooled.rate if pooled.clear_of_zero else 0.0


def pooled_clock(observations: Sequence[RateObservation]) -> RateObservation:
    """The clock the holds agree on and its standard error, clear of zero or not (σ
    infinite with fewer than ``MIN_POOLED`` holds timed).

    The holds' median, each weighed by its own precision (but none above the typical
    hold's), and its standard error from the holds' σ scaled by how far, in those σ, the
    typical hold lies from it. A hold's σ counts only its noise, and the transient a
    trim change leaves in a short hold turns its phasors too: on a disk with a load
    resonance and a −356 ppm clock (seed 9329) the first round's holds, 2 + 4 periods
    after steps of 100 mA, timed −1,700 to +2,800 ppm with σ under 300, while the next
    rounds' holds scattered about the clock by ±70 ppm: a weighted mean takes one hold's
    transient for the clock, an agreement test within each σ finds none. A median of the
    rates alone, with their spread for its error, weighs a hold timed to 10 ppm as one
    timed to 200: on a rough belt with a 215 ppm clock (seed 508770410) holds of 195 ± 9
    and 210 ± 10 ppm beside seven of 125-645 ± 30-219 pooled to 210 ± 53, not clear of
    zero; its wrap then fell unplaced in the verification, which read 0.17 m/s² of H1
    where the unit had 0.003.
    """
    none = RateObservation(0.0, math.inf)
    timed = [o for o in observations if math.isfinite(o.sigma) and abs(o.rate) <= MAX_RATE]
    if len(timed) < MIN_POOLED:
        return none
    rates = np.array([o.rate for o in timed])
    # No hold counts as timed more closely than the typical one: what biases a hold (a
    # transient, a speed error that took up part of the clock) does not shrink with its
    # noise. A Modbus unit's longest holds timed 5 ± 0.1 ppm of a −226 ppm clock (seed
    # 5020), its other 28 holds −190 to −260 ± 8.
    own = np.array([o.sigma for o in timed])
    sigmas = np.maximum(own, float(np.median(own)))
    weights = 1.0 / sigmas**2
    order = np.argsort(rates)
    cumulative = np.cumsum(weights[order])
    centre = float(rates[order][np.searchsorted(cumulative, cumulative[-1] / 2.0)])
    # How far the typical hold lies from it in its own σ (1 for honest σ, robustly).
    birge = max(1.0, 1.4826 * float(np.median(np.abs(rates - centre) / sigmas)))
    # A median's standard error is √(π/2) that of a mean of the same weights.
    sigma = 1.2533 * birge / math.sqrt(float(weights.sum()))
    return RateObservation(centre, sigma)
