"""Harmonic phasors of a segment, with the variance an estimator needs to weight them.

Plain correlation over whole periods (``station.dsp.demod``) is exact only
when every sample is present. Recordings lose frames and clip, so here the
phasors are a least-squares fit of DC plus orders 1..K over the samples that
exist: the missing ones then bias nothing, they only cost precision. The
variance comes from how the residual projects onto each order period by
period, which sees coloured noise (a ringing mode, unmodelled orders) that a
white-noise formula would miss.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.linalg import lapack

DEFAULT_ORDERS = 8
"""Orders reported by default."""

JOINT_ORDERS = 16
"""Orders fitted jointly whatever is reported (as far as the sampling resolves them).
A rough unit near a mode carries strong tonal ripple up to order 10 and beyond: left
out of the fit, it is counted as noise (inflating every variance tenfold) and leaks
into orders 1 and 2 through the holes lost and clipped samples leave."""

_MIN_PERIODS_FOR_SCATTER = 4
_RAYLEIGH_Z = 9.0
"""n·R̄² above which period-to-period turns have a direction (chance about e⁻⁹ ≈ 1e-4)."""


@dataclass(frozen=True)
class Harmonics:
    """Phasors H_k (k = 1..K) of one segment: A·cos(kθ + φ) gives H_k = A·e^{jφ}.

    ``variance[k-1]`` is E|Ĥ_k − H_k|² (real and imaginary parts each carry half).
    """

    phasors: NDArray[np.complex128]
    variance: NDArray[np.float64]
    dc: float
    residual_rms: float
    samples_used: int
    samples_missing: int
    # σ² of one sample's noise (dof-corrected): what the fitted orders leave, or with
    # ``demodulate(white_noise=True)`` what every order the sampling resolves leaves
    # (``_white_variance``); and each order's variance per unit of it: white noise alone
    # would give ``noise_variance * unit_variance``.
    noise_variance: float = math.nan
    unit_variance: NDArray[np.float64] | None = None
    # What the fitted model puts where samples are missing (NaN in the signal), in their
    # order: a clipped sample's part of each phasor is its true value minus this.
    imputed: NDArray[np.float64] | None = None

    def h(self, order: int) -> complex:
        return complex(self.phasors[order - 1])

    def var(self, order: int) -> float:
        return float(self.variance[order - 1])


def period_phasors(
    values: NDArray[np.float64],
    present: NDArray[np.bool_],
    angle: NDArray[np.float64],
    samples_per_period: float,
    orders: Sequence[int],
) -> NDArray[np.complex128]:
    """(periods, orders): 2/n·Σ values·exp(−j·k·angle) over each whole period.

    ``values`` is zero where a sample is not ``present``; n counts those that
    are. A remainder shorter than a period joins the last one.
    """
    periods = int(values.size // samples_per_period)
    starts = np.round(np.arange(periods) * samples_per_period).astype(np.intp)
    counts = np.maximum(np.add.reduceat(present.astype(np.float64), starts), 1.0)
    out = np.empty((periods, len(orders)), dtype=np.complex128)
    for j, k in enumerate(orders):
        out[:, j] = 2.0 * np.add.reduceat(values * np.exp(-1j * k * angle), starts) / counts
    return out


def _design(angle: NDArray[np.float64], orders: int) -> NDArray[np.float64]:
    k = np.arange(1, orders + 1)
    phase = np.outer(angle, k)
    return np.column_stack([np.ones_like(angle), np.cos(phase), np.sin(phase)])


def _nyquist(samples_per_period: float) -> int:
    """The highest order the sampling resolves without aliasing."""
    return math.floor((samples_per_period - 1e-9) / 2)


def _fitted_orders(orders: int, samples_per_period: float) -> int:
    """Orders 1..n that ``demodulate`` fits for ``orders`` asked: at least the joint ones,
    never beyond what the sampling resolves. ``SteadyProjection`` must project out the
    same harmonics, or the poles it measures take up what ``demodulate`` fits."""
    return max(1, min(max(orders, JOINT_ORDERS), _nyquist(samples_per_period)))


SEPARABLE = 1e-2
"""Share of a decay column's norm that must lie outside the steady harmonics' columns for
it to be fitted beside them. A ring slow enough to look steady over the window, at a
harmonic's frequency, is that harmonic over the window: fitted anyway, the two split the
signal into huge opposite parts (a development belt's phasor came out at 3e5 m/s²)."""


def _separable(steady: NDArray[np.float64], decay: NDArray[np.float64]) -> list[int]:
    """The columns of ``decay`` the window can tell from ``steady`` and from each other
    (``SEPARABLE``), taken in order: over a period or two, a slow ring and its sidebands
    are together nearly the harmonics themselves, though each alone is not."""
    q, _ = np.linalg.qr(steady)
    kept = []
    for j in range(decay.shape[1]):
        column = decay[:, j]
        apart = column - q @ (q.T @ column)
        size = float(np.linalg.norm(apart))
        if size > SEPARABLE * float(np.linalg.norm(column)):
            kept.append(j)
            q = np.column_stack([q, apart / size])
    return kept


@dataclass(frozen=True)
class SampleClock:
    """The times of a window's present samples, t = start + k for whole k (gaps where
    samples are missing), with k split as B·hi + lo: e^{jωt} is then a product of two
    short tables of exponentials, one entry of each per sample (``turns``).

    A pole search builds a decay's columns hundreds of times per hold, and a cosine and
    a sine per sample were most of its time: benchmark trial current_loop_lag@1703429826
    spent 17 s of its 58 building them. The product is as exact as the direct cosine,
    whose argument ωt is itself rounded to a few parts in 1e14 at the end of a hold.
    """

    times: NDArray[np.float64]  # (n,) samples since the change the decays start at
    grid: NDArray[np.float64]  # the tables' times: start + B·hi for every hi, then lo
    coarse: NDArray[np.intp]  # (n,) where in ``grid`` each sample's start + B·hi is
    fine: NDArray[np.intp]  # (n,) and where its lo is

    @classmethod
    def of(cls, present: NDArray[np.intp], offset: float) -> SampleClock:
        """The clock of samples at indices ``present`` (ascending), t = index + ``offset``."""
        times = (present + offset).astype(np.float64)
        if not present.size:
            empty = np.zeros(0, dtype=np.intp)
            return cls(times, np.zeros(0), empty, empty)
        k = present - present[0]
        block = math.isqrt(int(k[-1])) + 1
        hi = k // block
        blocks = int(hi[-1]) + 1
        grid = np.concatenate([times[0] + block * np.arange(blocks, dtype=np.float64),
                               np.arange(block, dtype=np.float64)])
        return cls(times, grid, hi, blocks + k % block)

    def tables(self, omegas: NDArray[np.float64]) -> NDArray[np.complex128]:
        """e^{jω·grid} for each of ``omegas`` (rows), from which ``turns`` builds e^{jωt}:
        all at once, since they are short and a call per pole cost more than them."""
        out: NDArray[np.complex128] = np.exp(1j * np.multiply.outer(omegas, self.grid))
        return out

    def turns(self, table: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """e^{jωt} at every sample, from ω's row of ``tables``."""
        out: NDArray[np.complex128] = table[self.coarse] * table[self.fine]
        return out


def _middle(times: NDArray[np.float64]) -> float:
    """The window's middle t̄, where a swept decay's frequency is referred (``_decay_design``)."""
    return 0.5 * (float(times[0]) + float(times[-1])) if times.size else 0.0


def _decay_design(clock: SampleClock, poles: Sequence[complex],
                  double: Sequence[complex] = (), sweeps: Sequence[float] = ()
                  ) -> NDArray[np.float64]:
    """Columns e^{σt}·cos φ and e^{σt}·sin φ per pole σ + jω (only the first if real),
    φ = ωt + ½·c·(t − t̄)² with c its entry of ``sweeps`` (0 where there is none), then
    the same times t for each pole of ``double`` (unswept); t the ``clock``'s.

    A swept pole's ω is its frequency at the window's middle t̄, where the window tells
    it best: referred to the change instead, a hold's frequency and sweep were one
    parameter seen twice (a test's chirp of 4 % came out 6 %, its decay half the truth).
    Built pole by pole: arrays of every pole at once are large enough for the allocator
    to hand back to the system and fault in again on every call (five times slower).
    """
    t = clock.times
    every = [*poles, *double]
    swept = list(sweeps) + [0.0] * (len(every) - len(sweeps))
    tables = clock.tables(np.array([p.imag for p in every]))
    middle = _middle(t)
    # A pole's sidebands share its rate and its sweep: each envelope and chirp once.
    envelopes: dict[tuple[float, bool], NDArray[np.float64]] = {}
    chirps: dict[float, NDArray[np.complex128]] = {}
    columns = []
    for i, (pole, sweep) in enumerate(zip(every, swept, strict=True)):
        doubled = i >= len(poles)
        envelope = envelopes.get((pole.real, doubled))
        if envelope is None:
            envelope = envelopes[(pole.real, doubled)] = np.exp(pole.real * t)
            if doubled:
                envelope *= t
        if pole.imag == 0.0:
            columns.append(envelope)
            continue
        ring = clock.turns(tables[i])
        if sweep:
            chirp = chirps.get(sweep)
            if chirp is None:
                chirp = chirps[sweep] = np.exp(0.5j * sweep * (t - middle) ** 2)
            ring *= chirp
        ring *= envelope
        columns.extend((ring.real, ring.imag))
    return np.column_stack(columns)


NOISE_DOF_SHARE = 0.25
"""Share of a segment's samples left as degrees of freedom when every order the sampling
resolves is fitted to find its noise (``_white_variance``); fewer orders where the
segment is too short for that."""


def _white_variance(angle: NDArray[np.float64], y: NDArray[np.float64],
                    x: NDArray[np.float64], *, fitted: int, nyquist: int,
                    sigma2: float) -> float:
    """σ² of one sample's noise: what is left once every periodic order the sampling
    resolves is fitted beside ``x`` (the fit's design, orders 1..``fitted`` in it), not
    only those; ``sigma2`` (what ``x`` alone leaves) where the segment is too short.

    Tonal ripple above the fitted orders is periodic: it is part of the motion and, over
    whole periods, does not project onto orders 1..K, so it is no part of their
    uncertainty. Counted as noise it inflated the phasors' σ: benchmark trial
    detent_torque+load_resonance@1838253693 (a belt whose chain modes at 317 and 608 Hz
    carried orders 17 to 21 of the cogging) left 0.01 to 2.3 (m/s²)² after 16 orders on
    its tangential axis against the sensor's 0.005 on the others, and every model's
    residuals came out at a thirtieth of the noise they were judged against.

    Jointly, since lost samples make the orders leak into each other; through the normal
    equations, whose cost is one product of the design with itself: a least-squares
    solver's SVD of 80 orders cost eight times the whole demodulation.
    """
    used = y.size
    more = min(nyquist, fitted + int((1.0 - NOISE_DOF_SHARE) * used - x.shape[1]) // 2)
    if more <= fitted:
        return sigma2
    # The design to ``more`` orders, with ``x``'s decay columns (those after its orders).
    wide = np.column_stack([_design(angle, more), x[:, 2 * fitted + 1:]])
    try:
        coef = np.linalg.solve(wide.T @ wide, wide.T @ y)
    except np.linalg.LinAlgError:
        return sigma2
    residual = y - wide @ coef
    # Orders with nothing in them only cost degrees of freedom: never above the narrow fit.
    return min(sigma2, float(residual @ residual) / float(used - wide.shape[1]))


SLOW_POWERS = 4
"""Each harmonic's phasor may move through a hold as a cubic in time (``slow_variance``).
A once-per-revolution modulation turns by a quarter revolution over the longest holds
(13 electrical periods of 50 per revolution); a quadratic left 15 times the noise of it on
a development disk (rotor_eccentricity@24: 1,708 times before), a cubic 1.9."""


def slow_variance(window: NDArray[np.float64], angle: NDArray[np.float64],
                  samples_per_period: float, slow_orders: int) -> float:
    """σ² of one sample that a hold leaves once its harmonics are let change slowly, or NaN
    where the hold is too short for it.

    A motion whose harmonics move through the hold (a once-per-revolution modulation
    turning with the rotor, a drifting clock's phase) is periodic to a model that takes
    each hold's mean phasors; only what this fit leaves is not. Orders 1..``slow_orders``
    (and the mean) change as a cubic in time; every higher order up to the sampling rate
    is fitted still, the orders beyond the Nyquist order included: on a belt with strong
    cogging, orders 15 to 20 at 34 Hz aliased to tones between the harmonics and left 30
    to 135 times the noise, periodic all the same (development
    detent_torque+flux_harmonics@821054). Aliases of a lower order add no column the fit
    can use, so the noise's degrees of freedom are counted from the design's rank.
    """
    ok = ~np.isnan(window)
    y = window[ok]
    x = angle[ok]
    used = y.size
    slow = min(slow_orders, _nyquist(samples_per_period))
    columns = SLOW_POWERS * (1 + 2 * slow)
    if used < 8 or slow < 1 or columns >= (1.0 - NOISE_DOF_SHARE) * used:
        return math.nan
    still = min(2 * _nyquist(samples_per_period),
                slow + int((1.0 - NOISE_DOF_SHARE) * used - columns) // 2)
    powers = np.vander(np.linspace(-1.0, 1.0, window.size)[ok], SLOW_POWERS,
                       increasing=True)  # 1, τ, τ², τ³
    moving = _design(x, slow)
    design = np.column_stack([_design(x, still),
                              *(moving * powers[:, j:j + 1] for j in range(1, SLOW_POWERS))])
    coef, _, rank, _ = np.linalg.lstsq(design, y, rcond=None)
    residual = y - design @ coef
    left: float = float(residual @ residual) / max(used - int(rank), 1)
    return left


_REFLECT_WORK = 64
"""Workspace of LAPACK's dormqr for one right-hand side: its block size."""
RANK_FLOOR = 1e-10
"""Smallest |diagonal of R| of the decays' QR, relative to the largest, at which their
columns count as independent: below it ``SteadyProjection.residual`` hands the fit to
lstsq, whose rank decision the pole search was developed with."""


@dataclass(frozen=True)
class SteadyProjection:
    """A window's samples with its steady harmonics (DC and every order ``demodulate``
    fits) projected out: what is left for a transient's decays to explain.

    For measuring the decays' poles, where the same window is fitted at many trial poles:
    the harmonics' part of the design never changes, so it is factored once and each
    trial solves only for the decays. Every decay column is kept, even one the window
    cannot tell from a harmonic (``SEPARABLE``), so that the residual moves smoothly with
    the poles.
    """

    basis: NDArray[np.float64]  # (n, m) orthonormal columns spanning the harmonics
    left: NDArray[np.float64]  # (n,) the samples less their projection on ``basis``
    clock: SampleClock  # the samples' times since the change the decays start at

    @classmethod
    def of(cls, signal: NDArray[np.float64], angle: NDArray[np.float64],
           samples_per_period: float, decay_from: float, orders: int = DEFAULT_ORDERS
           ) -> SteadyProjection:
        ok = ~np.isnan(signal)
        basis, _ = np.linalg.qr(_design(angle[ok], _fitted_orders(orders, samples_per_period)))
        y = signal[ok]
        return cls(basis, y - basis @ (basis.T @ y),
                   SampleClock.of(np.flatnonzero(ok), decay_from))

    @property
    def times(self) -> NDArray[np.float64]:
        return self.clock.times

    @property
    def columns(self) -> int:
        return int(self.basis.shape[1])

    def residual(self, decays: Sequence[complex], sweeps: Sequence[float] = ()
                 ) -> NDArray[np.float64]:
        """What the harmonics and ``decays`` (poles per sample, swept as ``demodulate``
        takes them) leave, sample by sample."""
        return self.fit(decays, sweeps).residual

    def fit(self, decays: Sequence[complex], sweeps: Sequence[float] = ()) -> DecayFit:
        """The decays fitted to what the harmonics leave: the residual, and what its
        slopes need (``DecayFit.slopes``)."""
        raw = _decay_design(self.clock, decays, sweeps=sweeps)
        d = raw - self.basis @ (self.basis.T @ raw)
        # A pole search calls this hundreds of times per hold: QR is about half the cost
        # of the SVD behind lstsq, and gives the same residual while the columns are
        # independent. Where they are not (a decay the window cannot tell from another or
        # from the harmonics), lstsq's minimum-norm solution keeps the residual smooth.
        # The residual is the samples reflected into the QR's basis, with the decays' part
        # zeroed, reflected back: Q itself is never formed (a residual of 10 decays took
        # a quarter less time: 278 against 384 µs over 1500 samples).
        reflectors, scales, _, _ = lapack.dgeqrf(d)
        diag = np.abs(np.diagonal(reflectors))
        if diag.min() > RANK_FLOOR * diag.max():
            inside, _, _ = lapack.dormqr("L", "T", reflectors, scales, self.left[:, None],
                                        _REFLECT_WORK)
            m = d.shape[1]
            amplitudes = lapack.dtrtrs(reflectors[:m, :m], inside[:m, 0])[0]
            inside[:m] = 0.0
            back, _, _ = lapack.dormqr("L", "N", reflectors, scales, inside, _REFLECT_WORK,
                                       overwrite_c=True)
            return DecayFit(self, tuple(decays), back[:, 0], raw, (reflectors, scales),
                            amplitudes)
        coef, *_ = np.linalg.lstsq(d, self.left, rcond=None)
        return DecayFit(self, tuple(decays), self.left - d @ coef, raw)


@dataclass(frozen=True)
class DecayFit:
    """Decays fitted by ``SteadyProjection.fit``: its residual, and the factors its
    slopes reuse (a least-squares search asks for both at the same poles)."""

    window: SteadyProjection
    decays: tuple[complex, ...]
    residual: NDArray[np.float64]
    design: NDArray[np.float64]  # the decays' columns before the harmonics are projected out
    # The projected columns' Householder QR (dgeqrf), None where they are not independent
    # (lstsq's minimum-norm fit, whose slope ``slopes`` does not give).
    factors: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None
    amplitudes: NDArray[np.float64] | None = None  # each column's fitted coefficient

    def slopes(self, tangents: NDArray[np.float64]) -> NDArray[np.float64] | None:
        """How ``residual`` moves with parameters that move the decays, (n, P):
        ``tangents`` (P, decays, 3) holds each parameter's derivative of each decay's
        rate, frequency and sweep. None where the columns are not independent.

        Golub and Pereyra's derivative of a variable projection, both its terms: the decays'
        fitted part moved with their amplitudes held, less what the fit already spans; and
        the amplitudes' own move, which is as large as the residual. Kaufman's shortcut
        drops the second, and on the holds of a belt, whose ringing is near the noise, it
        was 65 % off (median, 800 searches' Jacobians against central differences). A
        slope costs less than one ``residual``, where differencing costs one per
        parameter: a search of two to five parameters spent most of its evaluations on
        differences.
        """
        if self.factors is None or self.amplitudes is None:
            return None
        reflectors, scales = self.factors
        basis, t = self.window.basis, self.window.clock.times
        m = self.design.shape[1]
        h = 0.5 * (t - _middle(t)) ** 2
        # Each decay's fitted part is Re(z·w), z = e^{σt + jφ} its columns as one complex
        # number and w from its amplitudes; a move dσ, dω, dc turns z into
        # z·(t·dσ + j·t·dω + j·h·dc).
        first, second = [], []
        j = 0
        for pole in self.decays:
            first.append(j)
            second.append(j + 1 if pole.imag != 0.0 else -1)
            j += 1 + (pole.imag != 0.0)
        rings = np.array(second) >= 0
        z = self.design[:, first].astype(np.complex128)
        z[:, rings] += 1j * self.design[:, np.array(second)[rings]]
        w = self.amplitudes[first].astype(np.complex128)
        w[rings] -= 1j * self.amplitudes[np.array(second)[rings]]
        rate_freq = tangents[:, :, 0].T + 1j * tangents[:, :, 1].T  # (decays, P)
        sweep_rate = tangents[:, :, 2].T
        weighted = z * w
        g = (t[:, None] * (weighted @ rate_freq)).real
        g -= h[:, None] * (weighted @ sweep_rate).imag
        g -= basis @ (basis.T @ g)
        # The amplitudes' move: R⁻ᵀ of how each column's slope meets the residual, through Q.
        at_t, at_h = (t * self.residual) @ z, (h * self.residual) @ z
        meets = rate_freq * at_t[:, None] + 1j * sweep_rate * at_h[:, None]
        moved = np.zeros((m, g.shape[1]))
        moved[first] = meets.real
        moved[np.array(second)[rings]] = meets.imag[rings]
        work = _REFLECT_WORK * g.shape[1]
        reflected, _, _ = lapack.dormqr("L", "T", reflectors, scales, g, work)
        reflected[:m] = lapack.dtrtrs(reflectors[:m, :m], moved, trans=1)[0]
        back, _, _ = lapack.dormqr("L", "N", reflectors, scales, reflected, work,
                                   overwrite_c=True)
        out: NDArray[np.float64] = -back
        return out


def demodulate(
    signal: NDArray[np.float64],
    angle: NDArray[np.float64],
    samples_per_period: float,
    *,
    orders: int = DEFAULT_ORDERS,
    decays: Sequence[complex] = (),
    decay_from: float = 0.0,
    white_noise: bool = False,
    uncertain: Sequence[complex] = (),
    sweeps: Sequence[float] = (),
    taper: bool = False,
) -> Harmonics:
    """Least-squares phasors of orders 1..``orders`` referenced to ``angle``, fitted
    jointly with the orders up to ``JOINT_ORDERS``.

    ``signal`` holds NaN where a sample is missing or saturated. Orders at or
    above the Nyquist rate of the sampling are not fitted (they would alias).
    ``decays`` are poles per sample (λ·T, one of each conjugate pair) of a transient
    still ringing, whose change happened ``decay_from`` samples before the first:
    each is fitted with a free amplitude and phase, so it biases no phasor and costs
    the precision it shares with them. ``uncertain`` are those of the ``decays`` whose
    poles are only known to first order (measured, with an error): each is also fitted as
    a double pole (t·e^{λt}), which takes up a small error in it, and the phasors pay for
    what the pole's uncertainty costs them. ``sweeps`` (rad per sample², one per decay
    from the first, missing ones 0) are how fast each decay's frequency moves over the
    window: a ring on a spring that changes as the rotor turns is a chirp.
    ``taper`` weighs the samples by a Hann window (``hann``): content between the
    orders, a transient ringing at a mode's own frequency, then leaks into them through
    sidelobes falling as the cube of the distance instead of its first power, for
    about 1.5 times the variance (the variance returned is the weighted fit's).
    ``white_noise`` finds ``noise_variance`` beyond every resolvable order
    (``_white_variance``): the diagnosis weighs each phasor by it, while calibration
    reads only ``variance`` and does not pay for the wider fit.
    """
    if signal.shape != angle.shape or signal.ndim != 1:
        raise ValueError(f"signal {signal.shape} and angle {angle.shape} must match (1-D)")
    nyquist = _nyquist(samples_per_period)
    fitted = _fitted_orders(orders, samples_per_period)
    kept = min(orders, fitted)
    ok = ~np.isnan(signal)
    used = int(ok.sum())
    x = _design(angle[ok], fitted)
    # The same model where samples are missing: what the fit puts in their place.
    gaps = _design(angle[~ok], fitted)
    if decays:
        ring = _decay_design(SampleClock.of(np.flatnonzero(ok), decay_from), decays,
                             uncertain, sweeps)
        kept_ring = _separable(x, ring)
        x = np.column_stack([x, ring[:, kept_ring]])
        if gaps.shape[0]:
            gaps = np.column_stack([gaps, _decay_design(
                SampleClock.of(np.flatnonzero(~ok), decay_from), decays, uncertain,
                sweeps)[:, kept_ring]])
        else:
            gaps = np.zeros((0, x.shape[1]))
    if used <= x.shape[1]:
        raise ValueError(f"{used} samples cannot determine {x.shape[1]} coefficients")
    y = signal[ok]
    weight = hann(signal.size)[ok] if taper else None
    if weight is None:
        coef, *_ = np.linalg.lstsq(x, y, rcond=None)
    else:
        root = np.sqrt(weight)
        coef, *_ = np.linalg.lstsq(x * root[:, None], y * root, rcond=None)
    residual = y - x @ coef
    a, b = coef[1 : fitted + 1], coef[fitted + 1 : 2 * fitted + 1]
    phasors = np.full(orders, np.nan + 0j, dtype=np.complex128)
    phasors[:kept] = (a - 1j * b)[:kept]
    dof = used - x.shape[1]
    sigma2 = float(residual @ residual) / dof
    white = (_white_variance(angle[ok], y, x, fitted=fitted, nyquist=nyquist, sigma2=sigma2)
             if white_noise else sigma2)
    per_unit = np.diag(np.linalg.pinv(x.T @ x))
    cost = np.ones_like(per_unit)  # what the taper costs each coefficient's variance
    if weight is not None:
        # White noise through the weighted fit: the sandwich (XᵀWX)⁻¹XᵀW²X(XᵀWX)⁻¹.
        bread = np.linalg.pinv(x.T @ (x * weight[:, None]))
        tapered = np.diag(bread @ (x.T @ (x * (weight**2)[:, None])) @ bread)
        cost = tapered / np.where(per_unit > 0, per_unit, 1.0)
        per_unit = tapered
    unit = np.full(orders, np.nan)
    unit[:kept] = (per_unit[1 : fitted + 1] + per_unit[fitted + 1 : 2 * fitted + 1])[:kept]
    variance = sigma2 * unit
    periods = int(signal.size // samples_per_period)
    if periods >= _MIN_PERIODS_FOR_SCATTER:
        # Per-period projections of the residual: their scatter is the variance of one
        # period's phasor; the segment's phasor averages `periods` of them.
        r = np.zeros(signal.size)
        r[ok] = residual
        z = period_phasors(r, ok, angle, samples_per_period, range(1, kept + 1))
        scatter = np.sum(np.abs(z) ** 2, axis=0) / (periods * (periods - 1))
        # The flat fit's scatter, at what the taper costs each order.
        scatter = scatter * ((cost[1 : fitted + 1] + cost[fitted + 1 : 2 * fitted + 1])
                             / 2.0)[:kept]
        variance[:kept] = np.maximum(variance[:kept], scatter)
    return Harmonics(
        phasors=phasors,
        variance=variance,
        dc=float(coef[0]),
        residual_rms=math.sqrt(float(residual @ residual) / used),
        samples_used=used,
        samples_missing=int(signal.size - used),
        noise_variance=white,
        unit_variance=unit,
        imputed=gaps @ coef,
    )


def hann(samples: int) -> NDArray[np.float64]:
    """sin² over the window, zero just outside its ends: no sample weighs nothing."""
    n = np.arange(samples, dtype=np.float64) + 0.5
    return np.asarray(np.sin(np.pi * n / samples) ** 2, dtype=np.float64)


def phase_drift(
    per_period: NDArray[np.complex128], orders: Sequence[int]
) -> tuple[float, float]:
    """Relative frequency error seen in per-period phasors, and its standard error.

    Demodulated at f while the signal runs at f·(1 + δ), the order-k phasor
    turns by 2πkδ per period. Each order's turn is the angle of the summed
    lag-one products (strong periods count most), its standard error the
    scatter of the single turns around it; orders are pooled by inverse
    variance. A phasor that is only noise turns at random: an order whose turns
    show no preferred direction (Rayleigh's test) is left out, and callers must
    not correct a speed by a drift they cannot tell from zero. Returns (δ, σ);
    σ is infinite when nothing could be measured.
    """
    estimate, information = 0.0, 0.0
    for j, k in enumerate(orders):
        lags = per_period[1:, j] * np.conj(per_period[:-1, j])
        total = complex(np.sum(lags))
        if lags.size < 2 or total == 0:
            continue
        # How consistently the periods turn one way: about 1/√n for noise, near 1 for a tone.
        resultant = abs(total) / float(np.sum(np.abs(lags)))
        if lags.size * resultant**2 <= _RAYLEIGH_Z:
            continue  # Rayleigh's test: no preferred turn, this order says nothing
        turn = math.atan2(total.imag, total.real)
        # Circular standard deviation of one turn, then of their mean.
        error = math.sqrt(-2.0 * math.log(min(resultant, 1.0))) / math.sqrt(lags.size)
        scale = 2 * math.pi * k
        variance = max(error / scale, 1e-12) ** 2
        estimate += (turn / scale) / variance
        information += 1.0 / variance
    if information == 0.0:
        return 0.0, math.inf
    return estimate / information, 1.0 / math.sqrt(information)
