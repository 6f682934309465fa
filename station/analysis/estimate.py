"""Optimal trims from harmonic phasors measured at several trim points.

Two estimators, both pure functions of the points:

- the paper's (section 3): a weighted least-squares parabola of |H1|²
  against each offset and of |H2|² against the gain split, the trim at each
  vertex;
- a phase-coherent one: H1 and H2 are complex and, near the optimum, affine
  in the trims (eq. 16 is linear in the offsets and in the amplitude
  imbalance), so the affine maps are fitted from whatever points exist and
  solved for the offsets that null H1 and the split that then leaves the
  least H2, the paper's order. It uses the phase the paper throws away, so
  it needs no sweep through the minimum and no separable design.

Real sweeps go far enough for the response to turn nonlinear (a large rotor
oscillation, a clipped sensor). Both estimators therefore fit only the
largest neighbourhood of the optimum that the model explains within the
noise, found iteratively, and inflate their uncertainty by the Birge ratio
when even the smallest neighbourhood does not fit.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from station.core import GAIN_UNITY, Method, Trims
from station.dsp import h1_then_h2_null


class TrimAxis(StrEnum):
    """The three quantities a calibration sets; the gain split keeps the gain sum."""

    OFFSET_A = "offset_a_mA"
    OFFSET_B = "offset_b_mA"
    GAIN_SPLIT = "gain_split"

    @property
    def harmonic(self) -> int:
        """The order this trim acts on (offsets: 1st, imbalance: 2nd)."""
        return 2 if self is TrimAxis.GAIN_SPLIT else 1


AXES: tuple[TrimAxis, ...] = tuple(TrimAxis)

CONSISTENT_P = 0.01
"""A neighbourhood is accepted when its χ² is this probable or more."""

_MAX_REFITS = 6

_OFFSET_HELD_TOLERANCE_mA = 10.0
"""How far from the offsets' optimum a gain sweep may run before its split is suspect."""


def trim_coordinate(trims: Trims, axis: TrimAxis) -> float:
    """Where ``trims`` lie along ``axis``: an offset, or the gain split (half the
    difference, the sum held)."""
    if axis is TrimAxis.OFFSET_A:
        return trims.offset_a_mA
    if axis is TrimAxis.OFFSET_B:
        return trims.offset_b_mA
    return (trims.gain_a - trims.gain_b) / 2.0


@dataclass(frozen=True)
class TrimPoint:
    """One steady segment, reduced to what the estimators need."""

    trims: Trims
    h1: complex
    h1_var: float
    h2: complex
    h2_var: float
    # e^{jθ} of the rotor's mechanical angle at the hold's middle, where the drive reports
    # its angle: an eccentric rotor adds to each hold's phasors a part that turns with it.
    rotor: complex | None = None
    # The most the hold's samples over the sensor's rail could move each phasor (m/s²):
    # a bias of unknown sign, also in the variances, that ``_clipping_spread`` propagates.
    hidden: float = 0.0

    def coordinate(self, axis: TrimAxis) -> float:
        return trim_coordinate(self.trims, axis)

    def h(self, order: int) -> complex:
        return self.h1 if order == 1 else self.h2

    def var(self, order: int) -> float:
        return self.h1_var if order == 1 else self.h2_var

    @property
    def ripple(self) -> float:
        """How hard the rotor shakes here: what drives the response nonlinear."""
        return math.hypot(abs(self.h1), abs(self.h2))


@dataclass(frozen=True)
class TrimSigma:
    """Standard uncertainties of the four trims (same units)."""

    offset_a_mA: float
    offset_b_mA: float
    gain_a: float
    gain_b: float

    def as_dict(self) -> dict[str, float]:
        return {
            "offset_a_mA": self.offset_a_mA,
            "offset_b_mA": self.offset_b_mA,
            "gain_a": self.gain_a,
            "gain_b": self.gain_b,
        }


class Unsupported(Exception):
    """The data cannot support an estimate; the message says why."""


@dataclass(frozen=True)
class FitQuality:
    """How well a fit explains the points it used."""

    r_squared: float
    chi2_reduced: float  # 1 means the residuals are as large as the noise says
    dof: int
    points_used: int
    points_available: int
    residuals: tuple[float, ...]  # normalised (residual / sigma), per point used


@dataclass(frozen=True)
class ParabolaFit:
    """y = floor + curvature·(x − vertex)², y being |H_k|² in (m/s²)²."""

    axis: TrimAxis
    order: int
    vertex: float
    vertex_sigma: float
    curvature: float
    floor: float
    swept: tuple[float, float]
    x: tuple[float, ...]  # every point of the sweep
    y: tuple[float, ...]
    used: tuple[bool, ...]
    quality: FitQuality

    def curve(self, points: int = 41) -> tuple[tuple[float, float], ...]:
        """The fitted parabola sampled across the swept range, for plots."""
        xs = np.linspace(self.swept[0], self.swept[1], points)
        ys = self.floor + self.curvature * (xs - self.vertex) ** 2
        return tuple((float(a), float(b)) for a, b in zip(xs, ys, strict=True))


@dataclass(frozen=True)
class AffineFit:
    """H_k = intercept + Σ coefficient·(term − centre) over ``terms``."""

    order: int
    terms: tuple[Term, ...]
    centre: tuple[complex, ...]
    intercept: complex
    coefficients: tuple[complex, ...]
    quality: FitQuality


@dataclass(frozen=True)
class TrimEstimate:
    method: Method
    trims: Trims
    sigma: TrimSigma
    parabolas: tuple[ParabolaFit, ...] = ()
    affine: tuple[AffineFit, ...] = ()
    warnings: tuple[str, ...] = field(default_factory=tuple)


def _split_to_gains(split: float, gain_sum: float) -> tuple[float, float]:
    return gain_sum / 2.0 + split, gain_sum / 2.0 - split


def _gain_sum(points: Sequence[TrimPoint]) -> float:
    sums = {round(p.trims.gain_a + p.trims.gain_b) for p in points}
    return float(sums.pop()) if len(sums) == 1 else float(2 * GAIN_UNITY)


def _quality(
    residual: NDArray[np.float64], sigma: NDArray[np.float64], y: NDArray[np.float64],
    weights: NDArray[np.float64], *, params: int, available: int, per_point: int = 1,
) -> FitQuality:
    """Fit figures; ``per_point`` real equations per point (2 for a complex phasor)."""
    dof = residual.size - params
    chi2 = float(np.sum((residual / sigma) ** 2))
    mean = float(np.sum(weights * y) / np.sum(weights))
    total = float(np.sum(weights * (y - mean) ** 2))
    r2 = 1.0 - float(np.sum(weights * residual**2)) / total if total > 0 else 1.0
    return FitQuality(
        r_squared=r2,
        chi2_reduced=chi2 / dof if dof > 0 else float("nan"),
        dof=dof,
        points_used=int(residual.size) // per_point,
        points_available=available,
        residuals=tuple(float(r) for r in residual / sigma),
    )


def consistent_with_noise(q: FitQuality) -> bool:
    """Residuals no larger than the noise explains (chi² at least ``CONSISTENT_P`` probable)."""
    if q.dof <= 0:
        return True
    return float(stats.chi2.sf(q.chi2_reduced * q.dof, q.dof)) >= CONSISTENT_P


def _birge(q: FitQuality) -> float:
    """Scale for standard errors when the residuals exceed what the noise explains, or
    fall so far short of it that the points' own variances must be too large.

    The second is the largest scale the residuals allow at ``CONSISTENT_P``: the noise
    whose χ² would be that improbably small. A rough disk's holds (development seed
    1986512784) claimed ten times the variance their 19 points scattered by (χ²/dof 0.09
    and 0.15 over 28 degrees of freedom, a chance of 10⁻¹²): its σ of 5.1 mA failed a
    unit whose estimate was 0.07 mA from its optimum. Near χ²/dof = 1 nothing changes;
    over few degrees of freedom only a residual far below the noise scales at all.
    """
    if q.dof <= 0 or not math.isfinite(q.chi2_reduced):
        return 1.0
    if q.chi2_reduced >= 1.0:
        return math.sqrt(q.chi2_reduced)
    bound = q.chi2_reduced * q.dof / float(stats.chi2.ppf(CONSISTENT_P, q.dof))
    return math.sqrt(min(1.0, bound))


# --- the paper's parabolas -------------------------------------------------------------------


def sweep_along(points: Sequence[TrimPoint], axis: TrimAxis) -> list[TrimPoint]:
    """The largest set of points that vary only ``axis`` (the others held fixed)."""
    others = [a for a in AXES if a is not axis]
    groups: dict[tuple[float, ...], list[TrimPoint]] = {}
    for p in points:
        groups.setdefault(tuple(round(p.coordinate(a), 3) for a in others), []).append(p)
    best = max(groups.values(), key=lambda g: len({p.coordinate(axis) for p in g}), default=[])
    return best


@dataclass(frozen=True)
class _Parabola:
    coef: NDArray[np.float64]  # c0 + c1·u + c2·u², u = x − centre
    cov: NDArray[np.float64]
    centre: float
    quality: FitQuality

    @property
    def vertex(self) -> float:
        return float(self.centre - self.coef[1] / (2.0 * self.coef[2]))

    def vertex_sigma(self) -> float:
        c1, c2 = self.coef[1], self.coef[2]
        grad = np.array([0.0, -1.0 / (2 * c2), c1 / (2 * c2**2)])
        return float(math.sqrt(max(0.0, grad @ self.cov @ grad))) * _birge(self.quality)


def _fit_parabola(x: NDArray[np.float64], y: NDArray[np.float64], sigma: NDArray[np.float64],
                  available: int) -> _Parabola:
    centre = float(np.mean(x))
    u = x - centre
    design = np.column_stack([np.ones_like(u), u, u * u])
    w = 1.0 / sigma**2
    # Weights span many decades (|H|² near the null against the sweep's ends), so the
    # normal equations lose the curvature's variance to rounding; a column-scaled QR of
    # the whitened design keeps the covariance R⁻¹R⁻ᵀ positive by construction.
    whitened = design / sigma[:, None]
    scale = np.linalg.norm(whitened, axis=0)
    scale[scale == 0.0] = 1.0
    q, r = np.linalg.qr(whitened / scale)
    r_inv = np.linalg.inv(r) / scale[:, None]
    cov = r_inv @ r_inv.T
    coef = r_inv @ (q.T @ (y / sigma))
    residual = y - design @ coef
    quality = _quality(residual, sigma, y, w, params=3, available=available)
    return _Parabola(coef, np.asarray(cov, dtype=np.float64), centre, quality)


def _power(points: Sequence[TrimPoint], order: int) -> tuple[NDArray[np.float64], ...]:
    """|H|² with its noise bias removed, and its standard deviation.

    For H = μ + n with E|n|² = v: E|H|² = |μ|² + v and var|H|² = 2|μ|²v + v².
    """
    h = np.array([abs(p.h(order)) ** 2 for p in points])
    v = np.array([p.var(order) for p in points])
    y = h - v
    sigma = np.sqrt(2.0 * np.maximum(y, 0.0) * v + v * v)
    return y, np.maximum(sigma, 1e-12)


def _nearest_windows(
    x: NDArray[np.float64], fit: Callable[[NDArray[np.intp]], _Parabola], minimum: int
) -> tuple[NDArray[np.intp], _Parabola, bool]:
    """Largest window of points nearest the vertex that a parabola explains.

    Windows grow by distinct trim values, every repeat of a value kept together, and
    hold at least three values and ``minimum`` points: a sweep that returns to its
    nominal point between steps has many points at one value, and the points nearest
    the vertex could then hold only two values, which determine no parabola.
    """
    values = np.unique(x)
    order = np.arange(x.size)
    current = fit(order)
    chosen, accepted = order, consistent_with_noise(current.quality)

    def window(n: int) -> NDArray[np.intp]:
        nearest = values[np.argsort(np.abs(values - current.vertex), kind="stable")[:n]]
        return np.flatnonzero(np.isin(x, nearest))

    for _ in range(_MAX_REFITS):
        if current.coef[2] <= 0:
            break
        windows = [w for w in map(window, range(values.size, 2, -1)) if w.size >= minimum]
        pick: tuple[NDArray[np.intp], _Parabola, bool] | None = None
        for idx in windows:
            candidate = fit(idx)
            if candidate.coef[2] > 0 and consistent_with_noise(candidate.quality):
                pick = (idx, candidate, True)
                break
        if pick is None:
            idx = windows[-1] if windows else order
            pick = (idx, fit(idx), False)
        if np.array_equal(pick[0], chosen):
            current, accepted = pick[1], pick[2]
            break
        chosen, current, accepted = pick
    return chosen, current, accepted


def fit_parabola(points: Sequence[TrimPoint], axis: TrimAxis) -> tuple[ParabolaFit, list[str]]:
    """The paper's estimate along one axis, from its sweep; raises Unsupported."""
    sweep = sweep_along(points, axis)
    order = axis.harmonic
    x = np.array([p.coordinate(axis) for p in sweep])
    distinct = np.unique(x).size
    if distinct < 3:
        raise Unsupported(
            f"{axis.value}: too few points ({distinct} distinct values; a parabola needs 3)"
        )
    y, sigma = _power(sweep, order)

    def fit(idx: NDArray[np.intp]) -> _Parabola:
        return _fit_parabola(x[idx], y[idx], sigma[idx], x.size)

    minimum = min(x.size, 5)  # points in the smallest window (of three values or more)
    idx, best, accepted = _nearest_windows(x, fit, minimum)
    warnings: list[str] = []
    variance = float(best.cov[2, 2])
    if not (math.isfinite(variance) and variance >= 0.0):
        # A negative variance is a singular fit rounded the wrong way, not a measurement.
        raise Unsupported(f"{axis.value}: the sweep's points do not determine a parabola "
                          "(singular fit)")
    c2, c2_sigma = best.coef[2], math.sqrt(variance) * _birge(best.quality)
    if c2 <= 2.0 * c2_sigma:
        raise Unsupported(
            f"{axis.value}: flat parabola (curvature {c2:.3g} ± {c2_sigma:.2g} is not "
            "significantly positive)"
        )
    lo, hi = float(x.min()), float(x.max())
    vertex = best.vertex
    if not lo <= vertex <= hi:
        raise Unsupported(
            f"{axis.value}: the minimum {vertex:.1f} lies outside the swept range "
            f"[{lo:g}, {hi:g}]"
        )
    if not accepted:
        warnings.append(
            f"{axis.value}: even the {idx.size} points nearest the minimum fit worse than "
            f"the noise (reduced chi² {best.quality.chi2_reduced:.1f}); uncertainty inflated"
        )
    used = np.zeros(x.size, dtype=bool)
    used[idx] = True
    c0 = best.coef[0] - best.coef[1] ** 2 / (4 * c2)

    def vertex_of(moved: Sequence[TrimPoint]) -> NDArray[np.float64]:
        moved_y, moved_sigma = _power(moved, order)
        return np.array([_fit_parabola(x[idx], moved_y[idx], moved_sigma[idx], x.size).vertex])

    vertex_sigma = best.vertex_sigma()
    spread = _clipping_spread(vertex_of, sweep)
    if spread is not None:
        warnings.extend(f"{axis.value}: {note}" for note in
                        _clipping_note(spread, np.array([vertex_sigma])))
        vertex_sigma = float(np.hypot(vertex_sigma, spread[0]))
    return (
        ParabolaFit(
            axis=axis,
            order=order,
            vertex=vertex,
            vertex_sigma=vertex_sigma,
            curvature=float(c2),
            floor=float(c0),
            swept=(lo, hi),
            x=tuple(float(v) for v in x),
            y=tuple(float(v) for v in y),
            used=tuple(bool(u) for u in used),
            quality=best.quality,
        ),
        warnings,
    )


CLIPPED_NOTE = "clipping"
"""How an estimate's warning begins where clipping decides its σ (``_clipping_note``)."""
_TURNS = (1.0 + 0.0j, 1.0j, -1.0 + 0.0j, -1.0j)


def _clipping_spread(estimate: Callable[[Sequence[TrimPoint]], NDArray[np.float64]],
                     points: Sequence[TrimPoint]) -> NDArray[np.float64] | None:
    """How far an estimate can move, per quantity, on what its points' clipping hides.

    A unit whose waveform peaks over the rail whatever its trims misses the same
    phases in every hold, so what they hide is one bias, turned alike in each hold:
    the points' scatter cannot show it, and neither can a σ computed from it. So the
    estimate is made again, on the points it chose, with every point's phasor of one
    order moved by its ``hidden`` in each of four directions; the largest move is
    kept. None when nothing clipped; inf where a move leaves nothing to estimate.
    """
    if not any(p.hidden for p in points):
        return None
    base = estimate(points)
    worst = np.zeros_like(base)
    for order in (1, 2):
        for turn in _TURNS:
            moved = [_moved(p, order, p.hidden * turn) if p.hidden else p for p in points]
            try:
                worst = np.maximum(worst, np.abs(estimate(moved) - base))
            except (Unsupported, np.linalg.LinAlgError):
                return np.full_like(base, math.inf)
    return worst


def _moved(point: TrimPoint, order: int, bias: complex) -> TrimPoint:
    if order == 1:
        return replace(point, h1=point.h1 + bias)
    return replace(point, h2=point.h2 + bias)


def _clipping_note(spread: NDArray[np.float64], sd: NDArray[np.float64]) -> list[str]:
    """Said where what clipping may hide outweighs the noise in an estimate's σ."""
    if not np.any(spread > sd):
        return []
    return [f"{CLIPPED_NOTE}: what the samples over the sensor's rail may hide could move the "
            f"estimate by {', '.join(f'{v:.3g}' for v in spread)}; its σ carries it"]


def paper_estimate(points: Sequence[TrimPoint]) -> TrimEstimate:
    """The paper's method: one parabola per axis, trims at the vertices."""
    fits: list[ParabolaFit] = []
    warnings: list[str] = []
    for axis in AXES:
        fit, notes = fit_parabola(points, axis)
        fits.append(fit)
        warnings.extend(notes)
    a, b, g = fits
    gain_sweep = sweep_along(points, TrimAxis.GAIN_SPLIT)
    gain_a, gain_b = _split_to_gains(g.vertex, _gain_sum(gain_sweep))
    # The paper sweeps the split with the offsets already at their optimum; the 2nd
    # harmonic depends on the offsets too, so a split swept elsewhere is biased.
    held = gain_sweep[0].trims
    miss = math.hypot(held.offset_a_mA - a.vertex, held.offset_b_mA - b.vertex)
    if miss > max(_OFFSET_HELD_TOLERANCE_mA, 3 * math.hypot(a.vertex_sigma, b.vertex_sigma)):
        warnings.append(
            f"gain_split: swept with the offsets at ({held.offset_a_mA:g}, "
            f"{held.offset_b_mA:g}) mA, {miss:.0f} mA from their optimum; the paper's "
            "split assumes optimal offsets and may be biased (the coherent method is not)"
        )
    return TrimEstimate(
        method=Method.PAPER,
        trims=Trims(a.vertex, b.vertex, gain_a, gain_b),
        sigma=TrimSigma(a.vertex_sigma, b.vertex_sigma, g.vertex_sigma, g.vertex_sigma),
        parabolas=tuple(fits),
        warnings=tuple(warnings),
    )


# --- the phase-coherent estimator ------------------------------------------------------------


class Term(StrEnum):
    """Regressors of the complex harmonic models besides the intercept.

    The trims enter linearly. The mixing terms carry the leading nonlinearity:
    any quadratic stiffness or sensor curvature turns the fundamental ripple
    into a 2nd harmonic ∝ H1², and the 2nd back into the 1st ∝ conj(H1)·H2.
    Both vanish where H1 = 0, so they absorb the bend of far points without
    moving the null.

    The rotor terms carry what an eccentric rotor does to a short hold: its
    airgap varies once per revolution and scales the torque, and so every
    order's ripple, by 1 + ε·cos(θ − θ₀); a hold of a few periods cannot
    resolve the sidebands this puts 1/Nr of an order beside each order, so
    its phasor reads H·(1 + a·e^{jθ} + b·e^{−jθ}) at the rotor angle θ of
    the hold. Like the mixing terms they vanish where H does, and leave the
    null where the trims put it. On seed 528509142 (a disk with an eccentric
    rotor) they took the χ² per degree of freedom of all 19 points from 6.0
    to 1.3 on H1 and from 58 to 2.9 on H2.
    """

    OFFSET_A = "offset_a_mA"
    OFFSET_B = "offset_b_mA"
    GAIN_SPLIT = "gain_split"
    MIXING = "mixing"
    ROTOR = "rotor"
    ROTOR_BACK = "rotor_back"

    @property
    def axis(self) -> TrimAxis | None:
        return None if self in _NOT_TRIMS else TrimAxis(self.value)


_NOT_TRIMS = frozenset({Term.MIXING, Term.ROTOR, Term.ROTOR_BACK})


_PRIMARY: dict[int, tuple[Term, ...]] = {
    1: (Term.OFFSET_A, Term.OFFSET_B),
    2: (Term.GAIN_SPLIT,),
}
_OPTIONAL: dict[int, tuple[tuple[Term, ...], ...]] = {
    1: ((Term.GAIN_SPLIT,), (Term.MIXING,), (Term.ROTOR, Term.ROTOR_BACK)),
    2: ((Term.OFFSET_A, Term.OFFSET_B), (Term.MIXING,), (Term.ROTOR, Term.ROTOR_BACK)),
}


def _column(points: Sequence[TrimPoint], order: int, term: Term) -> NDArray[np.complex128]:
    axis = term.axis
    if axis is not None:
        return np.array([p.coordinate(axis) for p in points], dtype=np.complex128)
    if term is Term.ROTOR or term is Term.ROTOR_BACK:
        # Without the rotor's angle the column is zero, and ``_fit`` declines it.
        turns = np.array([0j if p.rotor is None else p.rotor for p in points])
        h = np.array([p.h(order) for p in points])
        out: NDArray[np.complex128] = h * (turns if term is Term.ROTOR else turns.conj())
        return out
    if order == 1:
        return np.array([p.h1.conjugate() * p.h2 for p in points])
    return np.array([p.h1 * p.h1 for p in points])


@dataclass(frozen=True)
class _Affine:
    order: int
    terms: tuple[Term, ...]
    centre: NDArray[np.complex128]
    coef: NDArray[np.complex128]  # intercept, then one per term
    cov: NDArray[np.float64]  # of the real (and, identically, the imaginary) parts
    quality: FitQuality

    def linear(self, coef: NDArray[np.complex128] | None = None
               ) -> tuple[complex, NDArray[np.complex128]]:
        """(H at zero trims with H1 = 0, slope per axis): the map the null solves."""
        c = self.coef if coef is None else coef
        # Centring is undone for every term; the mixing term then simply drops out,
        # because its regressor is zero wherever H1 is.
        const = complex(c[0] - c[1:] @ self.centre)
        return const, _trim_slopes(self.terms, c[1:])


def _trim_slopes(terms: Sequence[Term], coefficients: NDArray[np.complex128] | Sequence[complex]
                 ) -> NDArray[np.complex128]:
    """A map's slope per trim axis (zero where the map has no term for it)."""
    slopes = np.zeros(len(AXES), dtype=np.complex128)
    for term, slope in zip(terms, coefficients, strict=True):
        if term.axis is not None:
            slopes[AXES.index(term.axis)] = slope
    return slopes


def _fit(points: Sequence[TrimPoint], order: int, terms: Sequence[Term],
         available: int) -> _Affine | None:
    """Complex weighted least squares; None when a term does not vary in the points."""
    columns = [_column(points, order, t) for t in terms]
    for col in columns:
        if np.ptp(col.real) == 0 and np.ptp(col.imag) == 0:
            return None
    x = np.column_stack(columns) if columns else np.zeros((len(points), 0), np.complex128)
    centre = x.mean(axis=0)
    design = np.column_stack([np.ones(len(points)), x - centre])
    h = np.array([p.h(order) for p in points])
    var = np.array([p.var(order) for p in points])
    # Real and imaginary parts each carry half the variance: weight 2/var in |r|².
    w = 2.0 / var
    normal = design.conj().T @ (design * w[:, None])
    if np.linalg.cond(normal) > 1e12:
        return None
    inv = np.linalg.inv(normal)
    coef = inv @ (design.conj().T @ (w * h))
    residual = h - design @ coef
    sigma = np.sqrt(var / 2.0)
    quality = _quality(
        np.concatenate([residual.real, residual.imag]), np.concatenate([sigma, sigma]),
        np.concatenate([h.real, h.imag]), np.concatenate([w, w]),
        params=2 * design.shape[1], available=available, per_point=2,
    )
    return _Affine(order, tuple(terms), centre, coef, np.real(inv), quality)


def _chi2(q: FitQuality) -> float:
    return q.chi2_reduced * q.dof


def _select(points: Sequence[TrimPoint], order: int, available: int) -> _Affine | None:
    """Primary trims, plus each optional group that explains significantly more (F-test)."""
    terms = list(_PRIMARY[order])
    model = _fit(points, order, terms, available)
    if model is None:
        return None
    for group in _OPTIONAL[order]:
        wider = _fit(points, order, [*terms, *group], available)
        if wider is None or wider.quality.dof <= 2:
            continue
        extra = 2 * len(group)
        if model.quality.dof <= 0:
            continue
        f = ((_chi2(model.quality) - _chi2(wider.quality)) / extra) / (
            _chi2(wider.quality) / wider.quality.dof
        )
        if float(stats.f.sf(f, extra, wider.quality.dof)) < CONSISTENT_P:
            terms, model = [*terms, *group], wider
    return model


PhasorTerms = tuple[tuple[Term, ...], tuple[Term, ...]]
"""The terms of the H1 and of the H2 map."""


def phasor_terms(points: Sequence[TrimPoint]) -> PhasorTerms | None:
    """The terms each map needs over all ``points`` (primary, plus each optional group that
    explains significantly more); None where the points do not determine the maps."""
    models = [_select(points, order, len(points)) for order in (1, 2)]
    if models[0] is None or models[1] is None:
        return None
    return models[0].terms, models[1].terms


def phasor_misfit(points: Sequence[TrimPoint], terms: PhasorTerms) -> tuple[float, int]:
    """χ² of H1 and H2 against their affine maps of ``terms`` over all ``points``, and its
    degrees of freedom: what a turn of the phasors that the trims cannot explain adds.
    χ² infinite where the points do not determine the maps."""
    total, dof = 0.0, 0
    for order, order_terms in zip((1, 2), terms, strict=True):
        model = _fit(points, order, order_terms, len(points))
        if model is None or model.quality.dof <= 0:
            return math.inf, 0
        total += _chi2(model.quality)
        dof += model.quality.dof
    return total, dof


def _null(models: Sequence[_Affine], coefs: Sequence[NDArray[np.complex128]] | None = None
          ) -> NDArray[np.float64]:
    """Trims (offset A, offset B, split) where the fitted maps null H1, then least |H2|.

    The truth's definition (``h1_then_h2_null``), not least |H1|² + |H2|²:
    that would trade H1's null for H2's quadrature part, which no split reaches.
    """
    maps = {m.order: m.linear(None if coefs is None else coefs[i])
            for i, m in enumerate(models)}
    (h1, jac1), (h2, jac2) = maps[1], maps[2]
    return h1_then_h2_null(h1, h2, jac1, jac2)


def _null_covariance(models: Sequence[_Affine]) -> NDArray[np.float64]:
    """Propagate the fits' covariances through the null (numerical Jacobian)."""
    base = [m.coef.copy() for m in models]
    t0 = _null(models, base)
    columns: list[NDArray[np.float64]] = []
    blocks: list[NDArray[np.float64]] = []
    for k, m in enumerate(models):
        block = m.cov * _birge(m.quality) ** 2
        for part in (1.0, 1j):  # real and imaginary parts: independent, same covariance
            for j in range(m.coef.size):
                perturbed = [c.copy() for c in base]
                step = max(math.sqrt(block[j, j]), 1e-12)
                perturbed[k][j] += part * step
                columns.append((_null(models, perturbed) - t0) / step)
            blocks.append(block)
    jac = np.column_stack(columns)
    size = sum(b.shape[0] for b in blocks)
    full = np.zeros((size, size))
    at = 0
    for b in blocks:
        n = b.shape[0]
        full[at : at + n, at : at + n] = b
        at += n
    return np.asarray(jac @ full @ jac.T, dtype=np.float64)


SPLIT_SPREAD = 10.0
"""Splits closer than this (1/10000, the worst error asked of a gain) are one split: they
cannot determine H2's slope. Rounds re-centred on estimates 2 units apart (seed
717580667: 10356 and 10358) left the least-shaken five points "two" splits, whose H2
fit's R² of 0.34 failed a unit 0.6 gain units from its optimum."""


def _check_determined(points: Sequence[TrimPoint]) -> None:
    offsets = np.array(sorted({(p.trims.offset_a_mA, p.trims.offset_b_mA) for p in points}))
    if offsets.shape[0] < 3 or np.linalg.matrix_rank(offsets[1:] - offsets[0]) < 2:
        raise Unsupported(
            "offsets: the points do not span both offsets (need 3 non-collinear offset pairs)"
        )
    splits = [p.coordinate(TrimAxis.GAIN_SPLIT) for p in points]
    if max(splits) - min(splits) < SPLIT_SPREAD:
        raise Unsupported(f"gain split: the points hold a single gain split (need two "
                          f"{SPLIT_SPREAD:g} apart)")


def _determined(points: Sequence[TrimPoint]) -> bool:
    try:
        _check_determined(points)
    except Unsupported:
        return False
    return True


def _models(points: Sequence[TrimPoint], available: int) -> list[_Affine] | None:
    models = [_select(points, order, available) for order in (1, 2)]
    return None if any(m is None for m in models) else [m for m in models if m is not None]


def _looseness(models: Sequence[_Affine]) -> float:
    """The null's worst standard error, each axis in the worst error asked of it (1 mA,
    ``SPLIT_SPREAD`` of a split): what a fallback among neighbourhoods that all fit
    worse than the noise is chosen by."""
    sd = np.sqrt(np.maximum(np.diag(_null_covariance(models)), 0.0))
    worst = float(max(sd[0], sd[1], sd[2] / SPLIT_SPREAD))
    return worst if math.isfinite(worst) else math.inf


def coherent_estimate(points: Sequence[TrimPoint]) -> TrimEstimate:
    """Null the complex H1 and H2 with maps fitted over the least-shaken points.

    Points are taken in order of measured ripple, because the ripple is what
    bends the response; the largest such neighbourhood that the models
    explain within the noise is used. Where none is, the one whose null the maps
    determine best (``_looseness``, their σ inflated by the misfit): the smallest
    that still determined them held too little variation to pin H2's slope (seed
    879511937, a belt with reluctance torque and an eccentric rotor: three points, 5.7
    mA and 81 gain units off; its best, 0.3 mA and 0.5).
    """
    _check_determined(points)
    ranked = sorted(points, key=lambda p: p.ripple)
    fallback: tuple[list[TrimPoint], list[_Affine]] | None = None
    chosen: tuple[list[TrimPoint], list[_Affine]] | None = None
    loosest = math.inf
    for n in range(len(ranked), 2, -1):
        subset = ranked[:n]
        if not _determined(subset):
            break
        models = _models(subset, len(points))
        if models is None:
            continue
        if all(consistent_with_noise(m.quality) for m in models):
            chosen = (subset, models)
            break
        looseness = _looseness(models)
        if looseness <= loosest:
            fallback, loosest = (subset, models), looseness
    found = chosen or fallback
    if found is None:
        raise Unsupported("the trim points do not determine the harmonic maps")
    used, models = found
    warnings: list[str] = []
    if chosen is None:
        warnings.append(
            f"coherent: even the {len(used)} least-shaken points fit worse than the noise; "
            "uncertainty inflated"
        )
    t = _null(models)
    sd = np.sqrt(np.maximum(np.diag(_null_covariance(models)), 0.0))
    terms = [m.terms for m in models]

    def null_of(moved: Sequence[TrimPoint]) -> NDArray[np.float64]:
        refitted = [_fit(moved, m.order, terms[i], len(points)) for i, m in enumerate(models)]
        if any(m is None for m in refitted):
            raise Unsupported("the moved points do not determine the maps")
        return _null([m for m in refitted if m is not None])

    spread = _clipping_spread(null_of, used)
    if spread is not None:
        warnings.extend(_clipping_note(spread, sd))
        sd = np.hypot(sd, spread)
    gain_a, gain_b = _split_to_gains(float(t[2]), _gain_sum(points))
    for m in models:
        if m.quality.dof <= 0:
            warnings.append(f"coherent: H{m.order} has no redundant points; noise-only sigma")
    for axis, value in zip(AXES, t, strict=True):
        lo = min(p.coordinate(axis) for p in used)
        hi = max(p.coordinate(axis) for p in used)
        if not lo <= value <= hi:
            warnings.append(
                f"coherent: {axis.value} {value:.1f} is extrapolated beyond the points used "
                f"[{lo:g}, {hi:g}]"
            )
    return TrimEstimate(
        method=Method.COHERENT,
        trims=Trims(float(t[0]), float(t[1]), gain_a, gain_b),
        sigma=TrimSigma(float(sd[0]), float(sd[1]), float(sd[2]), float(sd[2])),
        affine=tuple(
            AffineFit(
                order=m.order,
                terms=m.terms,
                centre=tuple(complex(c) for c in m.centre),
                intercept=complex(m.coef[0]),
                coefficients=tuple(complex(c) for c in m.coef[1:]),
                quality=m.quality,
            )
            for m in models
        ),
        warnings=tuple(warnings),
    )


ESTIMATORS: dict[Method, Callable[[Sequence[TrimPoint]], TrimEstimate]] = {
    Method.COHERENT: coherent_estimate,
    Method.PAPER: paper_estimate,
}
"""Each method's estimator over the same points, in the order ``auto`` prefers them."""


def widest_explained(estimate: TrimEstimate, points: Sequence[TrimPoint],
                     steps: Sequence[tuple[float, float]]) -> tuple[float, float] | None:
    """The widest of ``steps`` (offset mA, split) whose star around the estimate the
    maps would still explain: its points no more shaken, by the maps' slopes, than the
    most shaken of the points the maps were fitted over. Wider steps tell the slopes
    more per hold, but a belt near resonance bends: its maps hold over its 7
    least-shaken points of 25, and a round of ±100 mA added there is left out of them
    (seed 1874937362, σ 4.4 mA then 6.5). None without phasor maps, and where even
    the narrowest would be more shaken."""
    fits = {fit.order: fit for fit in estimate.affine}
    if 1 not in fits or 2 not in fits or not points:
        return None
    used = min(fit.quality.points_used for fit in fits.values())
    ceiling = sorted(p.ripple for p in points)[min(used, len(points)) - 1]
    j1, j2 = (_trim_slopes(fits[k].terms, fits[k].coefficients) for k in (1, 2))
    for offset, split in sorted(steps, reverse=True):
        reach = max(math.hypot(abs(j1[axis] * step), abs(j2[axis] * step))
                    for axis, step in ((0, offset), (1, offset), (2, split)))
        if reach <= ceiling:
            return offset, split
    return None


@dataclass(frozen=True)
class Correction:
    """Where the estimate's maps, anchored on one more hold, put the null.

    ``trims`` are the drive's whole-number trims nearest that null with the least
    predicted |H1| (the offsets' four neighbours; the split rounds as gains do),
    ``h1_mps2`` and ``h2_mps2`` what the maps predict there.
    """

    null: Trims
    trims: Trims
    h1_mps2: float
    h2_mps2: float


CORRECTION_SIGMAS = 4.0
"""How far, in the estimate's own σ per axis, a correction may move the null: a
verification that puts it further than that says the maps' slopes are wrong, not where
the null is. A rough disk's split, σ 13 units, read an H2 of 0.40 m/s² (the plant: 0.40)
and was "corrected" 130 units on a slope a tenth of the truth's, to 3.4 m/s² (seed
2116120135)."""


def correction_from(estimate: TrimEstimate, held: TrimPoint) -> Correction | None:
    """The null as seen from a hold at the stored trims; None without phasor maps, or
    where it lies beyond ``CORRECTION_SIGMAS`` of the estimate's own.

    The sweep's maps are fitted over points many mA apart, where the response bends
    and a few-% error in the slopes moves the null by a fraction of a mA; a hold at the
    stored trims, near the null, reads what is left with the noise of one hold. A
    Newton step from it with the maps' slopes lands where the slopes' error times the
    (small) step is all that is left: on seed 1405145028 (a belt near resonance,
    0.12 m/s² of H1 per mA) the sweep's estimate was 0.36/0.47 mA off, stored
    0.55/0.88 mA off after rounding, and read 0.096 m/s² against a limit of 0.08.
    """
    fits = {fit.order: fit for fit in estimate.affine}
    if 1 not in fits or 2 not in fits:
        return None
    j1, j2 = (_trim_slopes(fits[k].terms, fits[k].coefficients) for k in (1, 2))
    at = np.array([held.coordinate(axis) for axis in AXES])
    null = at + h1_then_h2_null(held.h1, held.h2, j1, j2)
    t, sd = estimate.trims, estimate.sigma
    was = np.array([t.offset_a_mA, t.offset_b_mA, (t.gain_a - t.gain_b) / 2.0])
    reach = CORRECTION_SIGMAS * np.array([sd.offset_a_mA, sd.offset_b_mA, sd.gain_a])
    if not np.all(np.abs(null - was) <= reach):
        return None
    gain_sum = held.trims.gain_a + held.trims.gain_b
    gain_a, gain_b = _split_to_gains(float(null[2]), gain_sum)
    gains = (float(round(gain_a)), float(round(gain_b)))
    split = (gains[0] - gains[1]) / 2.0

    def predicted(a: float, b: float) -> tuple[float, float]:
        step = np.array([a, b, split]) - at
        return abs(held.h1 + complex(j1 @ step)), abs(held.h2 + complex(j2 @ step))

    corners = [(float(a), float(b)) for a in (math.floor(null[0]), math.ceil(null[0]))
               for b in (math.floor(null[1]), math.ceil(null[1]))]
    a, b = min(corners, key=lambda c: predicted(*c)[0])
    h1, h2 = predicted(a, b)
    return Correction(Trims(float(null[0]), float(null[1]), gain_a, gain_b),
                      Trims(a, b, *gains), h1, h2)
