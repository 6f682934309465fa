"""Trim estimators (station.analysis.estimate) on synthetic trim points.

The points come from a known complex-affine model of eq. (16): H1 is affine in
the offsets (the two act in quadrature) with a weak pull from the gain split,
H2 is affine in the split with a weak pull from the offsets plus the H1²
mixing a quadratic nonlinearity adds. Both vanish at a known optimum, so every
estimate can be judged against it.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import replace

import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis.estimate import (
    CLIPPED_NOTE,
    CORRECTION_SIGMAS,
    ESTIMATORS,
    SPLIT_SPREAD,
    TrimAxis,
    TrimPoint,
    Unsupported,
    coherent_estimate,
    correction_from,
    fit_parabola,
    paper_estimate,
    widest_explained,
)
from station.core import GAIN_UNITY, Method, Trims

# Offset A, offset B (mA), gain split (1/10000; gain A = 10000 + split, gain B = 10000 − split).
OPTIMUM: NDArray[np.float64] = np.array([-120.0, 55.0, -150.0])
J1 = np.array([2e-3 * np.exp(0.3j), 2e-3j * np.exp(0.3j), 3e-6 * np.exp(2.0j)])  # m/s² per unit
J2 = np.array([1e-5 * np.exp(0.5j), 1e-5 * np.exp(1.5j), 1.5e-4 * np.exp(1.0j)])
MIXING = 0.2  # H2 += MIXING·H1², 1/(m/s²)
NOISE_VAR = 6e-3**2  # E|n|² of each phasor: 300 µg/√Hz over a 0.5 s hold
OFFSETS = np.linspace(-500.0, 500.0, 11)
SPLITS = np.linspace(-3000.0, 3000.0, 11)


def trims_of(u: NDArray[np.float64]) -> Trims:
    return Trims(float(u[0]), float(u[1]), GAIN_UNITY + float(u[2]), GAIN_UNITY - float(u[2]))


def cross_design(
    *, a_at: float = 0.0, b_at: float = 0.0, split_at: tuple[float, float] = (0.0, 0.0),
    offsets: NDArray[np.float64] = OFFSETS, splits: NDArray[np.float64] = SPLITS,
) -> list[NDArray[np.float64]]:
    """The paper's sweeps: baseline, offset A (B held at ``b_at``), offset B (A held at
    ``a_at``), gain split (offsets held at ``split_at``); as (offset A, offset B, split)."""
    design = [np.zeros(3)]
    design += [np.array([o, b_at, 0.0]) for o in offsets]
    design += [np.array([a_at, o, 0.0]) for o in offsets]
    design += [np.array([split_at[0], split_at[1], s]) for s in splits]
    return design


def phasors(u: NDArray[np.float64]) -> tuple[complex, complex]:
    d = u - OPTIMUM
    h1 = complex(J1 @ d)
    return h1, complex(J2 @ d) + MIXING * h1 * h1


Response = Callable[[NDArray[np.float64]], tuple[complex, complex]]


def points(
    design: Iterable[NDArray[np.float64]], seed: int, *, response: Response = phasors,
    noise_var: float = NOISE_VAR,
) -> list[TrimPoint]:
    """Measured trim points: the model plus complex noise of variance ``noise_var``."""
    rng = np.random.default_rng(seed)
    out = []
    for u in design:
        h1, h2 = response(u)
        n = rng.normal(0.0, math.sqrt(noise_var / 2), 4)
        out.append(
            TrimPoint(trims_of(u), h1 + complex(n[0], n[1]), noise_var,
                      h2 + complex(n[2], n[3]), noise_var)
        )
    return out


def errors(trims: Trims) -> NDArray[np.float64]:
    """(offset A, offset B, split) minus the optimum; the split is half the gain difference."""
    split = (trims.gain_a - trims.gain_b) / 2
    found = np.array([trims.offset_a_mA, trims.offset_b_mA, split], dtype=np.float64)
    difference: NDArray[np.float64] = found - OPTIMUM
    return difference


# ------------------------------------------------------------------ phase-coherent


def test_coherent_estimate_of_the_paper_design_is_near_the_optimum() -> None:
    estimate = coherent_estimate(points(cross_design(), seed=0))
    assert estimate.method is Method.COHERENT
    err = errors(estimate.trims)
    assert abs(err[0]) < 1.0 and abs(err[1]) < 1.0 and abs(err[2]) < 10.0, err
    # The gain sum is kept: the split moves gain from one phase to the other.
    assert estimate.trims.gain_a + estimate.trims.gain_b == pytest.approx(2 * GAIN_UNITY)
    assert estimate.sigma.gain_a == estimate.sigma.gain_b
    assert [a.order for a in estimate.affine] == [1, 2]
    for fit in estimate.affine:
        assert fit.quality.points_used == fit.quality.points_available == 34
        assert len(fit.quality.residuals) == 2 * 34
        assert fit.quality.r_squared > 0.99


def test_coherent_sigma_matches_the_scatter_over_noise_seeds() -> None:
    """Pull (estimate − truth)/σ over many noise draws: a std near 1 means σ is honest."""
    pulls = []
    for seed in range(200):
        estimate = coherent_estimate(points(cross_design(), seed=seed))
        sigma = np.array([estimate.sigma.offset_a_mA, estimate.sigma.offset_b_mA,
                          estimate.sigma.gain_a])
        pulls.append(errors(estimate.trims) / sigma)
    pull = np.array(pulls)
    spread = pull.std(axis=0)
    assert np.all(spread > 0.5) and np.all(spread < 2.0), spread
    assert np.all(np.abs(pull.mean(axis=0)) < 0.3), pull.mean(axis=0)


def test_points_that_claim_far_more_noise_than_they_scatter_by_are_judged_by_their_scatter(
) -> None:
    """A rough unit's holds claimed ten times the variance their points scattered by:
    the σ follows the scatter, at the confidence the fits are judged by (an upper bound
    on it), where taken at their word the pulls would spread by 1/√10 = 0.32."""
    claimed = [coherent_estimate([replace(p, h1_var=10 * p.h1_var, h2_var=10 * p.h2_var)
                                  for p in points(cross_design(), seed=s)])
               for s in range(60)]
    pulls = np.array([errors(e.trims)[:2] / [e.sigma.offset_a_mA, e.sigma.offset_b_mA]
                      for e in claimed])
    spread = pulls.std(axis=0)
    assert np.all(spread > 0.5) and np.all(spread < 1.0), spread


def test_a_hold_at_the_stored_trims_corrects_them_to_the_drives_nearest_null() -> None:
    shift = np.array([0.42, -0.31, 0.2])  # the null between the drive's whole units

    def response(u: NDArray[np.float64]) -> tuple[complex, complex]:
        return phasors(u - shift)

    null = OPTIMUM + shift
    estimate = coherent_estimate(points(cross_design(), seed=0, response=response))
    # Stored 2.4 / 1.7 mA and 30 split units off, as a sweep on a bending unit may leave it.
    stored = np.round(null + np.array([2.4, -1.7, 30.0]))
    h1, h2 = response(stored)
    held = TrimPoint(trims_of(stored), h1, NOISE_VAR, h2, NOISE_VAR)
    correction = correction_from(estimate, held)
    assert correction is not None
    found = errors(correction.null) - shift
    assert abs(found[0]) < 0.05 and abs(found[1]) < 0.05 and abs(found[2]) < 1.0, found
    # The drive holds whole milliamperes and gain units: of the four corners round the
    # null, the one the maps say leaves the least H1, and what they say it leaves.
    t = correction.trims
    assert t == t.rounded()
    at = np.array([t.offset_a_mA, t.offset_b_mA, (t.gain_a - t.gain_b) / 2])
    corners = [abs(response(np.array([a, b, at[2]]))[0])
               for a in (math.floor(null[0]), math.ceil(null[0]))
               for b in (math.floor(null[1]), math.ceil(null[1]))]
    assert abs(response(at)[0]) == pytest.approx(min(corners))
    assert correction.h1_mps2 == pytest.approx(abs(response(at)[0]), rel=0.05)
    assert correction.h2_mps2 == pytest.approx(abs(response(at)[1]), rel=0.05, abs=1e-4)


def test_a_hold_that_puts_the_null_far_beyond_the_estimates_sigma_corrects_nothing() -> None:
    estimate = coherent_estimate(points(cross_design(), seed=0))
    # H2 as 200 split units would leave it: far beyond σ, the slopes are not to be trusted.
    h1, h2 = phasors(OPTIMUM)
    far = TrimPoint(trims_of(OPTIMUM), h1, NOISE_VAR, h2 + complex(J2[2]) * 200.0, NOISE_VAR)
    assert CORRECTION_SIGMAS * estimate.sigma.gain_a < 200.0
    assert correction_from(estimate, far) is None
    near = TrimPoint(trims_of(OPTIMUM), h1, NOISE_VAR, h2 + complex(J2[2]) * 1.0, NOISE_VAR)
    assert correction_from(estimate, near) is not None


def test_an_estimate_without_phasor_maps_corrects_nothing() -> None:
    estimate = paper_estimate(points(cross_design(split_at=(-120.0, 55.0)), seed=1))
    h1, h2 = phasors(OPTIMUM)
    assert correction_from(estimate, TrimPoint(trims_of(OPTIMUM), h1, 1.0, h2, 1.0)) is None


def test_coherent_estimate_uses_the_mixing_term_when_h2_bends_with_h1() -> None:
    estimate = coherent_estimate(points(cross_design(), seed=1))
    h2 = next(a for a in estimate.affine if a.order == 2)
    assert "mixing" in [t.value for t in h2.terms]


def _eccentric(points_: Sequence[TrimPoint], forward: complex, backward: complex,
               per_hold: float = 0.75) -> list[TrimPoint]:
    """The same holds on an eccentric rotor: each hold's ripple scaled by
    1 + forward·e^{jθ} + backward·e^{−jθ} at its rotor angle θ (``per_hold`` rad apart,
    a star hold of 6 periods on a 50-tooth rotor), which the hold carries."""
    out = []
    for n, p in enumerate(points_):
        turn = complex(math.cos(n * per_hold), math.sin(n * per_hold))
        scale = 1 + forward * turn + backward * turn.conjugate()
        out.append(replace(p, h1=p.h1 * scale, h2=p.h2 * scale, rotor=turn))
    return out


def test_an_eccentric_rotor_is_modelled_where_the_holds_carry_its_angle() -> None:
    # 4 % and 3 % of modulation: the widest points of the paper's design move by tens of
    # noise σ from hold to hold, and only the rotor terms explain it.
    design = cross_design()
    shaken = _eccentric(points(design, seed=3), 0.04 * np.exp(0.4j), 0.03 * np.exp(2.0j))
    estimate = coherent_estimate(shaken)
    for fit in estimate.affine:
        assert {"rotor", "rotor_back"} <= {t.value for t in fit.terms}
    err = errors(estimate.trims)
    assert abs(err[0]) < 1.0 and abs(err[1]) < 1.0 and abs(err[2]) < 10.0, err
    # Without the rotor's angle (a drive that does not report it) the terms cannot enter,
    # and the maps fit within the noise only over fewer points nearer the null.
    blind = coherent_estimate([replace(p, rotor=None) for p in shaken])
    for fit, seen in zip(blind.affine, estimate.affine, strict=True):
        assert not {"rotor", "rotor_back"} & {t.value for t in fit.terms}
        assert fit.quality.points_used < seen.quality.points_used
    # A round rotor needs no rotor terms.
    round_ = coherent_estimate(_eccentric(points(design, seed=3), 0j, 0j))
    for fit in round_.affine:
        assert not {"rotor", "rotor_back"} & {t.value for t in fit.terms}


def _saturating(limit: float) -> Response:
    """A rotor that shakes too hard stops following the model: beyond ``limit`` m/s²
    (300 mA of offset error) |H| grows at a third of the rate, its phase unchanged."""

    def squash(h: complex) -> complex:
        size = abs(h)
        if size <= limit:
            return h
        return h * (limit + (size - limit) / 3) / size

    def response(u: NDArray[np.float64]) -> tuple[complex, complex]:
        h1, h2 = phasors(u)
        return squash(h1), squash(h2)

    return response


def _plain_affine_null(pts: Sequence[TrimPoint]) -> NDArray[np.float64]:
    """What a fit of every point, bent or not, would give: the null of one affine map each."""
    u = np.array([[p.trims.offset_a_mA, p.trims.offset_b_mA, (p.trims.gain_a - p.trims.gain_b) / 2]
                  for p in pts])
    x = np.column_stack([np.ones(len(pts)), u])
    c1 = np.linalg.lstsq(x, np.array([p.h1 for p in pts]), rcond=None)[0]
    c2 = np.linalg.lstsq(x, np.array([p.h2 for p in pts]), rcond=None)[0]
    rows = np.vstack([c1[1:].real, c1[1:].imag, c2[1:].real, c2[1:].imag])
    rhs = -np.array([c1[0].real, c1[0].imag, c2[0].real, c2[0].imag])
    null: NDArray[np.float64] = np.linalg.lstsq(rows, rhs, rcond=None)[0] - OPTIMUM
    return null


def test_far_points_that_saturate_do_not_bias_the_coherent_estimate() -> None:
    """Tolerance: the acceptance's 3 mA and 30 gain units (a split of 30)."""
    response = _saturating(limit=300 * abs(J1[0]))
    worst = np.zeros(3)
    for seed in range(5):
        pts = points(cross_design(), seed=seed, response=response)
        worst = np.maximum(worst, np.abs(errors(coherent_estimate(pts).trims)))
        # The bend is real: taken at face value it moves the null by twice the tolerance.
        naive = np.abs(_plain_affine_null(pts))
        assert naive[0] > 6.0, naive
    assert worst[0] <= 3.0 and worst[1] <= 3.0 and worst[2] <= 30.0, worst


def test_far_points_that_saturate_do_not_bias_the_paper_offsets() -> None:
    response = _saturating(limit=300 * abs(J1[0]))
    design = cross_design(a_at=OPTIMUM[0], split_at=(OPTIMUM[0], OPTIMUM[1]))
    for seed in range(5):
        err = errors(paper_estimate(points(design, seed=seed, response=response)).trims)
        assert abs(err[0]) <= 3.0 and abs(err[1]) <= 3.0 and abs(err[2]) <= 30.0, err


def test_the_offsets_null_h1_even_where_h2_keeps_a_part_no_split_reaches() -> None:
    """The paper's order, which the truth follows: offsets null H1, the split then does
    what it can for H2. Here H2 leans on the offsets and keeps, at the optimum, a part in
    quadrature to what the split moves; least |H1|² + |H2|² would shave that part with
    the offsets and miss H1's null."""
    j2 = np.array([3e-4 * np.exp(0.2j), 3e-4 * np.exp(1.9j), J2[2]])
    unreachable = 0.3j * J2[2] / abs(J2[2])

    def response(u: NDArray[np.float64]) -> tuple[complex, complex]:
        d = u - OPTIMUM
        return complex(J1 @ d), complex(j2 @ d) + unreachable

    rows = np.vstack([J1.real, J1.imag, j2.real, j2.imag])
    rhs = -np.array([0.0, 0.0, unreachable.real, unreachable.imag])
    least_squares_error = np.linalg.lstsq(rows, rhs, rcond=None)[0]
    assert np.max(np.abs(least_squares_error[:2])) > 5.0, least_squares_error  # it matters
    for seed in range(3):
        err = errors(coherent_estimate(points(cross_design(), seed=seed,
                                              response=response)).trims)
        assert abs(err[0]) <= 1.0 and abs(err[1]) <= 1.0 and abs(err[2]) <= 10.0, err


def test_offsets_on_one_axis_only_are_refused() -> None:
    design = [u for u in cross_design() if u[1] == 0.0]  # no offset B sweep
    with pytest.raises(Unsupported, match="do not span both offsets"):
        coherent_estimate(points(design, seed=0))


def test_a_single_gain_split_is_refused() -> None:
    design = [u for u in cross_design() if u[2] == 0.0]  # no gain sweep
    with pytest.raises(Unsupported, match="single gain split"):
        coherent_estimate(points(design, seed=0))
    with pytest.raises(Unsupported, match="gain_split: too few points"):
        paper_estimate(points(design, seed=0))


def test_splits_closer_than_the_accuracy_asked_are_one_split() -> None:
    # Two rounds re-centred 2 units apart (seed 717580667) do not make a gain sweep.
    design = [u for u in cross_design() if u[2] == 0.0]
    design += [np.array([u[0], u[1], 2.0]) for u in design[:3]]
    with pytest.raises(Unsupported, match="single gain split"):
        coherent_estimate(points(design, seed=0))
    spread = [*design[:-3], *(np.array([u[0], u[1], SPLIT_SPREAD]) for u in design[:3])]
    assert coherent_estimate(points(spread, seed=0)).method is Method.COHERENT


def test_too_few_points_are_refused_by_both_methods() -> None:
    design = [np.array([0.0, 0.0, 0.0]), np.array([100.0, 100.0, 500.0])]
    with pytest.raises(Unsupported, match="need 3 non-collinear offset pairs"):
        coherent_estimate(points(design, seed=0))
    two_offsets = [np.array([o, 0.0, s]) for o in (-100.0, 100.0) for s in (0.0,)]
    with pytest.raises(Unsupported, match="offset_a_mA: too few points"):
        fit_parabola(points(two_offsets, seed=0), TrimAxis.OFFSET_A)


# ------------------------------------------------------------------------- paper


def test_paper_method_with_the_gain_sweep_at_optimal_offsets_finds_the_optimum() -> None:
    """The paper's own order: sweep A, then B at A's optimum, then the split at both."""
    design = cross_design(a_at=OPTIMUM[0], split_at=(OPTIMUM[0], OPTIMUM[1]))
    estimate = paper_estimate(points(design, seed=3))
    assert estimate.method is Method.PAPER
    err = errors(estimate.trims)
    assert abs(err[0]) < 2.0 and abs(err[1]) < 2.0 and abs(err[2]) < 20.0, err
    assert not any("gain_split: swept with the offsets" in w for w in estimate.warnings)
    assert estimate.trims.gain_a + estimate.trims.gain_b == pytest.approx(2 * GAIN_UNITY)


def test_paper_estimate_reports_curves_fit_quality_and_residuals() -> None:
    design = cross_design(a_at=OPTIMUM[0], split_at=(OPTIMUM[0], OPTIMUM[1]))
    estimate = paper_estimate(points(design, seed=3))
    assert [p.axis for p in estimate.parabolas] == list(TrimAxis)
    assert [p.order for p in estimate.parabolas] == [1, 1, 2]
    for fit in estimate.parabolas:
        curve = fit.curve()
        assert curve[0][0] == fit.swept[0] and curve[-1][0] == fit.swept[1]
        # The curve is the fitted parabola: lowest at the vertex, at the floor.
        xs = np.array([c[0] for c in curve])
        ys = np.array([c[1] for c in curve])
        assert ys.min() >= fit.floor - 1e-12
        assert abs(xs[np.argmin(ys)] - fit.vertex) <= (xs[1] - xs[0])
        assert fit.quality.r_squared > 0.95
        assert len(fit.quality.residuals) == fit.quality.points_used == sum(fit.used)
        assert len(fit.x) == len(fit.y) == len(fit.used) == fit.quality.points_available


def test_paper_gain_split_swept_away_from_the_optimal_offsets_is_flagged() -> None:
    estimate = paper_estimate(points(cross_design(), seed=3))
    warning = [w for w in estimate.warnings if w.startswith("gain_split: swept with the offsets")]
    assert len(warning) == 1
    assert "(0, 0) mA" in warning[0]


def test_a_flat_parabola_is_refused() -> None:
    """Offset A that does not move H1 at all: nothing to locate a minimum in."""

    def blind_to_a(u: NDArray[np.float64]) -> tuple[complex, complex]:
        return phasors(np.array([OPTIMUM[0], u[1], u[2]]))

    pts = points(cross_design(), seed=0, response=blind_to_a)
    with pytest.raises(Unsupported, match="offset_a_mA: flat parabola"):
        fit_parabola(pts, TrimAxis.OFFSET_A)
    with pytest.raises(Unsupported, match="flat parabola"):
        paper_estimate(pts)


def test_a_minimum_outside_the_swept_range_is_refused() -> None:
    design = cross_design(offsets=np.linspace(0.0, 500.0, 11))
    with pytest.raises(Unsupported, match=r"offset_a_mA: the minimum -1\d\d\.\d lies outside"):
        fit_parabola(points(design, seed=0), TrimAxis.OFFSET_A)


def test_a_sweep_that_returns_to_nominal_still_determines_its_parabola() -> None:
    """Calibration schedules revisit the nominal trims, and a real unit is not quite the
    same at each visit. When the minimum lies beside nominal, the points nearest it are
    mostly those repeats, which no parabola fits within their noise; the smallest
    window must still hold three distinct values (it once held two: a singular fit)."""
    vertex = -250.0
    design = [np.array([0.0, 0.0, s]) for s in SPLITS] + [np.zeros(3)] * 3

    def response(u: NDArray[np.float64]) -> tuple[complex, complex]:
        return 0j, complex(J2[2] * (u[2] - vertex)) + 1e-3

    pts = points(design, seed=4, response=response, noise_var=NOISE_VAR / 1e4)
    visits = [i for i, u in enumerate(design) if u[2] == 0.0]
    for i, drift in zip(visits, (1.0, 1.05, 0.95, 1.08), strict=True):
        pts[i] = replace(pts[i], h2=pts[i].h2 * drift)
    fit, warnings = fit_parabola(pts, TrimAxis.GAIN_SPLIT)
    assert len(set(np.asarray(fit.x)[np.asarray(fit.used)])) >= 3
    assert abs(fit.vertex - vertex) < 30.0, fit.vertex
    assert any("fit worse than the noise" in w for w in warnings), warnings


# ------------------------------------------------------------------ clipping


def _clipped(pts: Sequence[TrimPoint], hidden: float) -> list[TrimPoint]:
    """The points as holds whose samples over the rail may hide ``hidden`` of each phasor
    (its variance included, as ``Measured.point`` gives them)."""
    return [replace(p, h1_var=p.h1_var + hidden**2, h2_var=p.h2_var + hidden**2, hidden=hidden)
            for p in pts]


def test_a_bias_every_clipped_hold_shares_is_carried_by_the_coherent_sigma() -> None:
    # Seed 1742693704: the same phases over the rail in every hold moved every H1 alike, by
    # 0.42 m/s², and the null 15 mA, with a σ of 1 mA from the holds' scatter.
    hidden = 0.05
    clean = points(cross_design(), seed=4)
    plain, clipped = coherent_estimate(clean), coherent_estimate(_clipped(clean, hidden))
    assert not any(CLIPPED_NOTE in w for w in plain.warnings)
    assert any(w.startswith(f"{CLIPPED_NOTE}: ") for w in clipped.warnings)
    biased = coherent_estimate([replace(p, h1=p.h1 + hidden) for p in clean])
    moved = np.abs(errors(biased.trims) - errors(plain.trims))
    sigma = clipped.sigma
    assert moved[0] > 5 * plain.sigma.offset_a_mA  # the bias is no noise the fit could see
    assert sigma.offset_a_mA >= moved[0] and sigma.offset_b_mA >= moved[1]
    assert sigma.gain_a >= moved[2]


def test_holds_that_did_not_clip_leave_the_estimate_as_it_was() -> None:
    clean = points(cross_design(), seed=5)
    assert coherent_estimate(_clipped(clean, 0.0)) == coherent_estimate(clean)


def test_a_parabolas_vertex_sigma_carries_what_clipping_may_hide() -> None:
    design = cross_design(a_at=OPTIMUM[0], split_at=(OPTIMUM[0], OPTIMUM[1]))
    clean = points(design, seed=3)
    plain, clipped = paper_estimate(clean), paper_estimate(_clipped(clean, 0.3))
    # Every hold weighed alike by what it may hide: near the same vertices.
    moved = np.abs(errors(clipped.trims) - errors(plain.trims))
    assert moved[0] < 3 * plain.sigma.offset_a_mA and moved[1] < 3 * plain.sigma.offset_b_mA
    assert clipped.sigma.offset_a_mA > 3 * plain.sigma.offset_a_mA
    assert any(f"{TrimAxis.OFFSET_A.value}: {CLIPPED_NOTE}: " in w for w in clipped.warnings)


# ------------------------------------------------------------------ rounds for σ

STEPS = [(100.0, 1000.0), (30.0, 300.0), (10.0, 100.0)]


def test_a_unit_whose_maps_hold_everywhere_gets_the_widest_star() -> None:
    pts = points(cross_design(), seed=6)
    assert widest_explained(coherent_estimate(pts), pts, STEPS) == (100.0, 1000.0)


def test_a_unit_that_bends_gets_the_widest_star_its_maps_still_explain() -> None:
    # Beyond 30 mA of offset error the response bends: the maps hold over the points
    # nearer the null, and a star of ±100 mA there would be left out of them.
    response = _saturating(limit=30 * abs(J1[0]))
    design = [OPTIMUM + np.array([a, b, s]) for a, b, s in itertools.product(
        (-60.0, -20.0, 0.0, 20.0, 60.0), (-20.0, 0.0, 20.0), (-200.0, 0.0, 200.0))]
    pts = points(design, seed=7, response=response)
    estimate = coherent_estimate(pts)
    assert estimate.affine[0].quality.points_used < len(pts)
    assert widest_explained(estimate, pts, STEPS) == (30.0, 300.0)


def test_an_estimate_without_phasor_maps_asks_for_no_star() -> None:
    design = cross_design(a_at=OPTIMUM[0], split_at=(OPTIMUM[0], OPTIMUM[1]))
    pts = points(design, seed=3)
    assert widest_explained(paper_estimate(pts), pts, STEPS) is None


def test_every_method_has_one_estimator_and_says_whether_it_needs_the_drive_angle() -> None:
    assert set(ESTIMATORS) == set(Method)
    assert next(iter(ESTIMATORS)) is Method.COHERENT  # what "auto" prefers
    assert Method.COHERENT.needs_angle and not Method.PAPER.needs_angle
