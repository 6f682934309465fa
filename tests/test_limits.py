"""The recipe's limits applied to a run's numbers (station.limits)."""

from __future__ import annotations

import math
from dataclasses import replace
from importlib.resources import files

import numpy as np
import pytest

from station.analysis.estimate import (
    AffineFit,
    FitQuality,
    ParabolaFit,
    Term,
    TrimAxis,
    TrimEstimate,
    TrimSigma,
)
from station.core import Method, Trims
from station.limits import (
    drift,
    drift_warnings,
    estimate_checks,
    reduction_db,
    ripple_checks,
    summary,
    trims_within,
    unsupported,
    verdict_for,
    worst_r_squared,
)
from station.recipes import Limits, parse_recipe
from station.runs import LimitCheck, LimitName, Ripple, Verdict


def default_limits() -> Limits:
    text = (files("recipes") / "default.toml").read_text(encoding="utf-8")
    return parse_recipe(text, source="default.toml").limits


LIMITS = default_limits()
# As shipped: offsets within ±250 mA, gains 8500..11500, sigma 3 mA / 30, R² at least 0.99,
# after-limits 0.08 / 0.25 m/s², reduction 6 dB, drift 15 mA / 100.

GOOD_SIGMA = TrimSigma(1.0, 1.5, 12.0, 12.0)


BEYOND_NOISE = 50.0
"""A reduced chi² no noise explains: fit quality is then judged by R² (see worst_r_squared)."""


def quality(r_squared: float, dof: int, chi2: float = BEYOND_NOISE) -> FitQuality:
    return FitQuality(
        r_squared=r_squared, chi2_reduced=chi2, dof=dof, points_used=dof + 2,
        points_available=dof + 2, residuals=(),
    )


def affine(order: int, r_squared: float, dof: int, chi2: float = BEYOND_NOISE) -> AffineFit:
    return AffineFit(
        order=order,
        terms=(Term.OFFSET_A, Term.OFFSET_B) if order == 1 else (Term.GAIN_SPLIT,),
        centre=(0j, 0j) if order == 1 else (0j,),
        intercept=0.1 + 0.2j,
        coefficients=(0.001 + 0j, 0.001j) if order == 1 else (0.0001 + 0j,),
        quality=quality(r_squared, dof, chi2),
    )


def parabola(axis: TrimAxis, r_squared: float, dof: int) -> ParabolaFit:
    return ParabolaFit(
        axis=axis, order=axis.harmonic, vertex=0.0, vertex_sigma=1.0, curvature=1e-6,
        floor=0.0, swept=(-500.0, 500.0), x=(), y=(), used=(), quality=quality(r_squared, dof),
    )


def coherent(
    *, sigma: TrimSigma = GOOD_SIGMA,
    fits: tuple[tuple[float, int], ...] = ((0.995, 10), (0.9991, 4)),
) -> TrimEstimate:
    """A coherent estimate whose affine fits have the given (R², dof), in order."""
    return TrimEstimate(
        method=Method.COHERENT,
        trims=Trims(12.3, -40.6, 10150.2, 9849.8),
        sigma=sigma,
        affine=tuple(affine(order, r2, dof) for order, (r2, dof) in enumerate(fits, 1)),
    )


STORED = Trims(12.0, -41.0, 10150.0, 9850.0)


def by_name(checks: tuple[LimitCheck, ...]) -> dict[LimitName | str, LimitCheck]:
    names = [c.name for c in checks]
    assert len(names) == len(set(names)), names
    return {c.name: c for c in checks}


# --- the estimate -----------------------------------------------------------------------------


def test_default_recipe_limits_are_what_these_tests_assume() -> None:
    assert (LIMITS.offset_bound_mA, LIMITS.gain_min, LIMITS.gain_max) == (250.0, 8500, 11500)
    assert (LIMITS.max_offset_sigma_mA, LIMITS.max_gain_sigma, LIMITS.min_fit_r_squared) == (
        3.0, 30.0, 0.99,
    )
    assert (LIMITS.max_h1_after_mps2, LIMITS.max_h2_after_mps2, LIMITS.min_reduction_db) == (
        0.08, 0.25, 6.0,
    )


def test_a_sound_estimate_within_bounds_passes_every_check_with_its_figures() -> None:
    checks = by_name(estimate_checks(LIMITS, coherent(), STORED))
    assert set(checks) == {
        LimitName.ESTIMATE, LimitName.OFFSET_A, LimitName.OFFSET_B, LimitName.GAIN_A,
        LimitName.GAIN_B, LimitName.OFFSET_SIGMA, LimitName.GAIN_SIGMA, LimitName.FIT_R2,
    }
    assert all(c.passed is True for c in checks.values())
    assert checks[LimitName.ESTIMATE].note == "coherent"
    assert checks[LimitName.OFFSET_A] == LimitCheck(
        LimitName.OFFSET_A, 12.0, -250.0, 250.0, "mA", True
    )
    assert checks[LimitName.OFFSET_B].value == -41.0  # the stored value, not the estimate
    assert (checks[LimitName.GAIN_A].low, checks[LimitName.GAIN_A].high) == (8500, 11500)
    assert checks[LimitName.OFFSET_SIGMA].value == 1.5  # the worse of the two
    assert checks[LimitName.GAIN_SIGMA].value == 12.0
    fit = checks[LimitName.FIT_R2]
    assert (fit.value, fit.low, fit.high, fit.unit) == (0.995, 0.99, None, "")  # the worst fit
    assert verdict_for(checks.values()) is Verdict.PASS


@pytest.mark.parametrize(
    ("stored", "failing"),
    [
        (Trims(250.5, 0.0), LimitName.OFFSET_A),
        (Trims(0.0, -251.0), LimitName.OFFSET_B),
        (Trims(0.0, 0.0, 11501.0, 8499.0), LimitName.GAIN_A),
        (Trims(0.0, 0.0, 11501.0, 8499.0), LimitName.GAIN_B),
    ],
)
def test_a_trim_outside_the_recipe_bounds_fails_its_check(
    stored: Trims, failing: LimitName
) -> None:
    checks = by_name(estimate_checks(LIMITS, coherent(), stored))
    assert checks[failing].passed is False
    assert verdict_for(checks.values()) is Verdict.FAIL


def test_trims_exactly_at_the_bounds_pass() -> None:
    checks = estimate_checks(LIMITS, coherent(), Trims(250.0, -250.0, 11500.0, 8500.0))
    assert all(c.passed is True for c in checks)


def test_trims_within_the_bounds_are_exactly_those_whose_bound_checks_pass() -> None:
    assert trims_within(LIMITS, Trims(250.0, -250.0, 11500.0, 8500.0))
    for outside in (Trims(250.5, 0.0), Trims(0.0, -251.0), Trims(0.0, 0.0, 11501.0, 8499.0),
                    Trims(math.nan, 0.0)):
        assert not trims_within(LIMITS, outside)


def test_sigma_limits_fail_on_the_worse_of_the_two_trims() -> None:
    checks = by_name(
        estimate_checks(LIMITS, coherent(sigma=TrimSigma(0.5, 3.2, 10.0, 31.0)), STORED)
    )
    assert checks[LimitName.OFFSET_SIGMA].passed is False
    assert checks[LimitName.OFFSET_SIGMA].value == 3.2
    assert checks[LimitName.OFFSET_SIGMA].high == 3.0
    assert checks[LimitName.GAIN_SIGMA].passed is False
    assert checks[LimitName.GAIN_SIGMA].value == 31.0
    others = [c for n, c in checks.items()
              if n not in (LimitName.OFFSET_SIGMA, LimitName.GAIN_SIGMA)]
    assert all(c.passed is True for c in others)


def test_fits_within_the_noise_pass_whatever_their_r_squared() -> None:
    """Points close to the null vary little against the noise: a low R² means nothing there."""
    estimate = TrimEstimate(
        method=Method.COHERENT, trims=Trims(), sigma=GOOD_SIGMA,
        affine=(affine(1, 0.5, 10, chi2=1.1), affine(2, 0.97, 6, chi2=0.9)),
    )
    check = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert check.passed is True and check.value is None
    assert check.note == "every fit within the noise"


def test_only_fits_beyond_the_noise_are_judged_by_r_squared() -> None:
    estimate = TrimEstimate(
        method=Method.COHERENT, trims=Trims(), sigma=GOOD_SIGMA,
        affine=(affine(1, 0.5, 10, chi2=1.0), affine(2, 0.98, 6)),
    )
    check = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert (check.value, check.passed) == (0.98, False)


def test_fit_limit_judges_the_worst_fit_with_points_to_spare() -> None:
    estimate = coherent(fits=((0.97, 6), (0.999, 3)))
    fit = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert (fit.value, fit.low, fit.high, fit.passed) == (0.97, 0.99, None, False)
    estimate = coherent(fits=((0.999, 6), (0.985, 3)))  # the worst is not always the first
    fit = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert (fit.value, fit.passed) == (0.985, False)


def test_a_fit_exactly_at_the_minimum_passes() -> None:
    estimate = coherent(fits=((0.99, 6), (0.999, 3)))
    fit = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert (fit.value, fit.passed) == (0.99, True)


def test_a_poor_chi2_does_not_fail_a_fit_that_explains_the_unit() -> None:
    # At this signal-to-noise a model right to 0.1 % fails chi² by far; R² decides.
    estimate = TrimEstimate(
        method=Method.COHERENT,
        trims=Trims(12.3, -40.6, 10150.2, 9849.8),
        sigma=GOOD_SIGMA,
        affine=(affine(1, 0.9995, 10, chi2=400.0), affine(2, 0.998, 4, chi2=90.0)),
    )
    fit = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert (fit.value, fit.passed) == (0.998, True)


def test_a_fit_without_spare_points_is_not_the_worst_fit() -> None:
    # A fit with dof 0 explains its points trivially (or its R² is NaN): it must not decide.
    assert worst_r_squared(coherent(fits=((math.nan, 0), (0.995, 2)))) == 0.995
    assert worst_r_squared(coherent(fits=((0.2, 0), (0.995, 2)))) == 0.995


def test_a_non_finite_r_squared_among_the_fits_with_spare_points_is_nan_and_fails() -> None:
    estimate = coherent(fits=((0.999, 6), (math.nan, 3)))
    assert math.isnan(worst_r_squared(estimate) or 0.0)
    fit = by_name(estimate_checks(LIMITS, estimate, STORED))[LimitName.FIT_R2]
    assert fit.passed is False
    assert summary((fit,)) == "failed fit_r_squared = nan (limit 0.99)"


def test_fit_limit_does_not_apply_when_no_fit_had_points_to_spare() -> None:
    estimate = coherent(fits=((math.nan, 0), (0.5, 0)))
    assert worst_r_squared(estimate) is None
    checks = by_name(estimate_checks(LIMITS, estimate, STORED))
    fit = checks[LimitName.FIT_R2]
    assert fit.passed is None and fit.value is None
    assert fit.low == 0.99
    assert "no fit had points to spare" in fit.note
    assert verdict_for(checks.values()) is Verdict.PASS


def test_parabola_fits_of_the_paper_method_are_judged_too() -> None:
    estimate = TrimEstimate(
        method=Method.PAPER,
        trims=Trims(),
        sigma=GOOD_SIGMA,
        parabolas=(
            parabola(TrimAxis.OFFSET_A, 0.999, 6),
            parabola(TrimAxis.OFFSET_B, 0.95, 6),
            parabola(TrimAxis.GAIN_SPLIT, 0.1, 0),  # no dof: ignored
        ),
    )
    assert worst_r_squared(estimate) == 0.95
    checks = by_name(estimate_checks(LIMITS, estimate, Trims()))
    assert checks[LimitName.ESTIMATE].note == "paper"
    assert (checks[LimitName.FIT_R2].value, checks[LimitName.FIT_R2].passed) == (0.95, False)


def test_a_tighter_recipe_fails_an_estimate_the_default_passes() -> None:
    strict = replace(LIMITS, offset_bound_mA=10.0, min_fit_r_squared=0.998)
    assert verdict_for(estimate_checks(LIMITS, coherent(), STORED)) is Verdict.PASS
    checks = by_name(estimate_checks(strict, coherent(), STORED))
    assert checks[LimitName.OFFSET_A].passed is False  # 12 mA > 10
    assert checks[LimitName.OFFSET_B].passed is False
    assert checks[LimitName.FIT_R2].passed is False  # 0.995 < 0.998
    assert checks[LimitName.FIT_R2].low == 0.998
    assert checks[LimitName.GAIN_A].passed is True


def test_unsupported_estimate_is_a_failed_estimate_check_with_the_reason() -> None:
    check = unsupported("offsets: too few points")
    assert (check.name, check.passed, check.note) == (
        LimitName.ESTIMATE, False, "offsets: too few points",
    )
    assert verdict_for([check]) is Verdict.FAIL


# --- the ripple -------------------------------------------------------------------------------
# Each harmonic is judged on its own: after-limit, and a reduction of at least 6 dB
# (20·log10(before/after)) unless it was within its after-limit before calibration.


def test_a_ripple_beyond_its_limit_fails_whether_it_is_a_python_or_a_numpy_number() -> None:
    # The plant's optimum comes as numpy values: a numpy False is not ``False``, and a
    # population benchmark counted units left with 0.54 m/s² of H2 as ones to pass.
    after = Ripple(np.float64(0.01), np.float64(0.54))
    checks = by_name(ripple_checks(LIMITS, Ripple(np.float64(9.0), np.float64(17.0)), after))
    assert checks[LimitName.H2_AFTER].passed is False
    assert type(checks[LimitName.H2_AFTER].value) is float
    assert verdict_for(checks.values()) is Verdict.FAIL
    assert summary(list(checks.values())).startswith("failed h2_after_mps2")


def test_ripple_checks_pass_a_unit_brought_within_the_after_limits() -> None:
    before, after = Ripple(0.6, 0.5), Ripple(0.03, 0.1)
    checks = by_name(ripple_checks(LIMITS, before, after))
    assert set(checks) == {LimitName.H1_AFTER, LimitName.H2_AFTER, LimitName.H1_REDUCTION,
                           LimitName.H2_REDUCTION}
    assert checks[LimitName.H1_AFTER] == LimitCheck(
        LimitName.H1_AFTER, 0.03, None, 0.08, "m/s²", True
    )
    assert checks[LimitName.H2_AFTER] == LimitCheck(
        LimitName.H2_AFTER, 0.1, None, 0.25, "m/s²", True
    )
    h1, h2 = checks[LimitName.H1_REDUCTION], checks[LimitName.H2_REDUCTION]
    assert h1.value == pytest.approx(26.0206, abs=1e-4)  # 20·log10(0.6 / 0.03) = 20·log10(20)
    assert h2.value == pytest.approx(13.9794, abs=1e-4)  # 20·log10(0.5 / 0.1) = 20·log10(5)
    for reduction in (h1, h2):
        assert (reduction.low, reduction.high, reduction.unit, reduction.passed) == (
            6.0, None, "dB", True,
        )
    assert verdict_for(checks.values()) is Verdict.PASS


def test_a_verification_that_clipped_is_judged_on_the_most_it_could_have() -> None:
    # Seed 1742693704: 0.014 m/s² of H1 read at ±16 g, where the plant has 0.42; the samples
    # over the rail could hide up to 0.4 of it.
    before, after = Ripple(0.6, 0.5), Ripple(0.014, 0.1)
    checks = by_name(ripple_checks(LIMITS, before, after, hidden=0.4))
    h1, h2 = checks[LimitName.H1_AFTER], checks[LimitName.H2_AFTER]
    assert h1.value == pytest.approx(0.414) and h1.passed is False
    assert h2.value == pytest.approx(0.5) and h2.passed is False
    assert "0.014 and 0.1 m/s² measured, and up to 0.4 more" in h1.note
    assert checks[LimitName.H1_REDUCTION].value == pytest.approx(20 * math.log10(0.6 / 0.414))
    # A little clipping that cannot decide the verdict changes nothing but the figures.
    checks = by_name(ripple_checks(LIMITS, before, after, hidden=0.01))
    assert verdict_for(checks.values()) is Verdict.PASS
    assert checks[LimitName.H1_AFTER].value == pytest.approx(0.024)


def test_after_limits_fail_each_harmonic_on_its_own() -> None:
    checks = by_name(ripple_checks(LIMITS, Ripple(1.0, 2.0), Ripple(0.09, 0.1)))
    assert checks[LimitName.H1_AFTER].passed is False
    assert checks[LimitName.H2_AFTER].passed is True
    checks = by_name(ripple_checks(LIMITS, Ripple(1.0, 2.0), Ripple(0.01, 0.26)))
    assert checks[LimitName.H1_AFTER].passed is True
    assert checks[LimitName.H2_AFTER].passed is False


def test_a_harmonic_reduced_less_than_the_recipe_minimum_fails() -> None:
    before, after = Ripple(0.5, 0.3), Ripple(0.02, 0.16)
    checks = by_name(ripple_checks(LIMITS, before, after))
    assert checks[LimitName.H1_REDUCTION].passed is True  # 27.96 dB
    h2 = checks[LimitName.H2_REDUCTION]
    assert h2.value == pytest.approx(5.4600, abs=1e-4)  # 20·log10(0.3 / 0.16)
    assert h2.passed is False
    assert checks[LimitName.H2_AFTER].passed is True  # within 0.25, yet not quieter enough
    assert verdict_for(checks.values()) is Verdict.FAIL


def test_the_reduction_minimum_comes_from_the_recipe() -> None:
    before, after = Ripple(0.0, 0.5), Ripple(0.0, 0.5 / 10 ** (7.0 / 20))  # 7 dB quieter
    h2 = by_name(ripple_checks(LIMITS, before, after))[LimitName.H2_REDUCTION]
    assert h2.value == pytest.approx(7.0)
    assert h2.passed is True
    stricter = replace(LIMITS, min_reduction_db=7.5)
    h2 = by_name(ripple_checks(stricter, before, after))[LimitName.H2_REDUCTION]
    assert (h2.low, h2.passed) == (7.5, False)


def test_reduction_db_is_the_amplitude_ratio_in_decibels() -> None:
    assert reduction_db(1.0, 0.1) == pytest.approx(20.0)
    assert reduction_db(0.3, 0.6) == pytest.approx(-6.0206, abs=1e-4)  # louder after
    assert reduction_db(1.0, 0.0) == math.inf
    assert reduction_db(0.0, 0.1) == -math.inf


def test_reduction_does_not_apply_to_a_harmonic_already_within_its_after_limit() -> None:
    # H1 was quiet already (0.05 <= 0.08); H2 was loud (0.6 > 0.25) and came down 21.6 dB.
    before, after = Ripple(0.05, 0.6), Ripple(0.049, 0.05)
    checks = by_name(ripple_checks(LIMITS, before, after))
    h1 = checks[LimitName.H1_REDUCTION]
    assert h1.passed is None
    assert h1.value == pytest.approx(reduction_db(0.05, 0.049))  # still recorded: 0.18 dB
    assert "within its after-limit before calibration" in h1.note
    assert checks[LimitName.H2_REDUCTION].passed is True
    assert verdict_for(checks.values()) is Verdict.PASS


def test_a_unit_within_both_after_limits_before_has_no_reduction_to_meet() -> None:
    checks = by_name(ripple_checks(LIMITS, Ripple(0.08, 0.25), Ripple(0.079, 0.26)))
    assert checks[LimitName.H1_REDUCTION].passed is None
    assert checks[LimitName.H2_REDUCTION].passed is None
    assert checks[LimitName.H2_AFTER].passed is False  # but the after-limits still apply


def test_a_quiet_second_harmonic_does_not_excuse_a_first_that_barely_moved() -> None:
    # H2 at its floor; H1 loud before and only 3 dB quieter after.
    checks = by_name(ripple_checks(LIMITS, Ripple(0.14, 0.2), Ripple(0.0705, 0.05)))
    assert checks[LimitName.H2_REDUCTION].passed is None
    assert checks[LimitName.H1_REDUCTION].passed is False
    assert checks[LimitName.H1_AFTER].passed is True


def test_reduction_does_not_apply_without_a_baseline() -> None:
    checks = by_name(ripple_checks(LIMITS, None, Ripple(0.01, 0.01)))
    for name in (LimitName.H1_REDUCTION, LimitName.H2_REDUCTION):
        assert (checks[name].value, checks[name].passed) == (None, None)
        assert checks[name].note == "no baseline was measured"
    assert verdict_for(checks.values()) is Verdict.PASS


# --- verdict and summary ----------------------------------------------------------------------


def test_verdict_fails_on_any_failed_check_and_ignores_those_that_did_not_apply() -> None:
    passed = LimitCheck(LimitName.H1_AFTER, 0.01, None, 0.08, "m/s²", True)
    skipped = LimitCheck(LimitName.H1_REDUCTION, None, 6.0, None, "dB", None)
    failed = LimitCheck(LimitName.H2_AFTER, 0.3, None, 0.25, "m/s²", False)
    assert verdict_for([passed, skipped]) is Verdict.PASS
    assert verdict_for([]) is Verdict.PASS
    assert verdict_for([passed, skipped, failed]) is Verdict.FAIL


def test_summary_names_every_failed_limit_with_its_value_and_bound() -> None:
    checks = (
        *ripple_checks(LIMITS, Ripple(1.0, 1.0), Ripple(0.5, 0.1)),
        unsupported("gain split: the points hold a single gain split (need two 10 apart)"),
    )
    text = summary(checks)
    assert text.startswith("failed ")
    assert "h1_after_mps2 = 0.5 m/s² (limit 0.08)" in text
    assert "reduction" not in text  # 6.02 and 20 dB: both passed
    assert "estimate: gain split: the points hold a single gain split (need two 10 apart)" in text
    assert "h2_after_mps2" not in text


def test_summary_quotes_the_lower_bound_for_a_value_below_it() -> None:
    checks = ripple_checks(LIMITS, Ripple(0.0, 0.3), Ripple(0.0, 0.2))
    assert summary(checks) == "failed h2_reduction_db = 3.522 dB (limit 6)"


def test_summary_says_all_limits_met_when_nothing_failed() -> None:
    assert summary(estimate_checks(LIMITS, coherent(), STORED)) == "all limits met"


def test_summary_names_a_limit_failed_by_a_nan_value() -> None:
    estimate = coherent(sigma=TrimSigma(math.nan, 1.0, 10.0, 10.0))
    checks = estimate_checks(LIMITS, estimate, STORED)
    assert by_name(checks)[LimitName.OFFSET_SIGMA].passed is False
    assert summary(checks) == "failed offset_sigma_mA = nan mA (limit 3)"


@pytest.mark.parametrize(
    ("sigma", "name"),
    [
        (TrimSigma(math.nan, 1.0, 10.0, 10.0), LimitName.OFFSET_SIGMA),
        (TrimSigma(1.0, math.nan, 10.0, 10.0), LimitName.OFFSET_SIGMA),
        (TrimSigma(1.0, 1.0, math.nan, 10.0), LimitName.GAIN_SIGMA),
        (TrimSigma(1.0, 1.0, 10.0, math.nan), LimitName.GAIN_SIGMA),
    ],
)
def test_a_nan_uncertainty_on_either_trim_fails_the_sigma_limit(
    sigma: TrimSigma, name: LimitName
) -> None:
    checks = by_name(estimate_checks(LIMITS, coherent(sigma=sigma), STORED))
    assert checks[name].passed is False
    assert math.isnan(checks[name].value or 0.0)
    assert verdict_for(checks.values()) is Verdict.FAIL


# --- drift (field service) --------------------------------------------------------------------


def test_drift_is_new_minus_previous_per_trim() -> None:
    assert drift(Trims(10.0, -5.0, 10100.0, 9900.0), Trims(4.0, 5.0, 10000.0, 10050.0)) == Trims(
        -6.0, 10.0, -100.0, 150.0
    )


def test_drift_warnings_name_each_trim_that_moved_past_the_recipe() -> None:
    previous = Trims(10.0, -5.0, 10100.0, 9900.0)
    new = Trims(30.0, 5.0, 9950.0, 10000.0)  # +20 mA, +10 mA, -150, +100
    warnings = drift_warnings(LIMITS, previous, new)
    assert warnings == [
        "offset A drifted by +20 mA since the last calibration "
        "(from 10 to 30; the recipe warns past 15)",
        "gain A drifted by -150 since the last calibration "
        "(from 10100 to 9950; the recipe warns past 100)",
    ]


def test_no_drift_warning_within_the_recipe() -> None:
    previous = Trims(10.0, -5.0, 10100.0, 9900.0)
    assert drift_warnings(LIMITS, previous, previous) == []
    assert drift_warnings(LIMITS, previous, Trims(25.0, -20.0, 10200.0, 9800.0)) == []
    looser = replace(LIMITS, max_drift_offset_mA=50.0, max_drift_gain=500.0)
    assert drift_warnings(looser, previous, Trims(40.0, 5.0, 9950.0, 10000.0)) == []
