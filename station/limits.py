"""The recipe's pass/fail limits applied to a run's numbers: pure, no I/O.

Every limit yields a ``LimitCheck`` whether it passed or not, so a record
shows how close a passing unit came, and QA can compute capability from the
same figures the verdict used. A check that cannot apply (a reduction
demanded of a unit that was already within its limits) is kept with
``passed=None`` and says why.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence
from dataclasses import replace

from station.analysis.estimate import FitQuality, TrimEstimate, consistent_with_noise
from station.core import Trims
from station.recipes import Limits
from station.runs import LimitCheck, LimitName, Ripple, Verdict

_MPS2 = "m/s²"
_GAIN = "1/10000"


def _within(name: LimitName, value: float, low: float | None, high: float | None,
            unit: str) -> LimitCheck:
    # Plain Python values: numpy's booleans are not ``False`` to ``is False``, so a
    # failed check on a numpy value would pass every verdict that asks it.
    value = float(value)
    passed = (low is None or value >= low) and (high is None or value <= high)
    return LimitCheck(name, value, low, high, unit, passed)


def fit_qualities(estimate: TrimEstimate) -> list[FitQuality]:
    return [p.quality for p in estimate.parabolas] + [a.quality for a in estimate.affine]


def worst_r_squared(estimate: TrimEstimate) -> float | None:
    """The smallest share of variation explained among the fits that the noise cannot excuse.

    A fit fails on quality only when both things are true: its residuals are
    larger than the noise explains (the estimators' own chi² test), and it
    explains too small a share of the variation (R²). Either alone says
    nothing: the harmonics are measured so precisely that a model right to a
    tenth of a percent fails chi² by far, while points close to the null
    vary so little against the noise that even a perfect model has a low R².
    Fits with no spare points decide nothing; None when no fit is left.
    """
    fits = [q for q in fit_qualities(estimate) if q.dof > 0]
    if not fits:
        return None
    beyond_noise = [q for q in fits if not consistent_with_noise(q)]
    if any(not math.isfinite(q.r_squared) for q in beyond_noise):
        return math.nan
    if not beyond_noise:
        return math.inf  # every residual within the noise: nothing left unexplained
    return min(q.r_squared for q in beyond_noise)


def _worst(*values: float) -> float:
    """The largest value, or NaN if any is NaN (builtin max would hide a NaN after the first)."""
    return math.nan if any(math.isnan(v) for v in values) else max(values)


def bound_checks(limits: Limits, trims: Trims) -> tuple[LimitCheck, ...]:
    """The recipe's bounds on each trim: what the drive may be given at all."""
    bound = limits.offset_bound_mA
    return (
        _within(LimitName.OFFSET_A, trims.offset_a_mA, -bound, bound, "mA"),
        _within(LimitName.OFFSET_B, trims.offset_b_mA, -bound, bound, "mA"),
        _within(LimitName.GAIN_A, trims.gain_a, limits.gain_min, limits.gain_max, _GAIN),
        _within(LimitName.GAIN_B, trims.gain_b, limits.gain_min, limits.gain_max, _GAIN),
    )


def trims_within(limits: Limits, trims: Trims) -> bool:
    """Whether a recipe with these limits may store ``trims`` (a unit whose optimum lies
    outside must fail, whatever else it does)."""
    return all(check.passed for check in bound_checks(limits, trims))


def estimate_checks(
    limits: Limits, estimate: TrimEstimate, stored: Trims
) -> tuple[LimitCheck, ...]:
    """Limits that are judged before anything is written: trims in bounds, a sound fit.

    ``stored`` are the trims as the drive would hold them (whole units).
    """
    sigma = estimate.sigma
    checks = [
        LimitCheck(LimitName.ESTIMATE, None, None, None, "", True, estimate.method.value),
        *bound_checks(limits, stored),
        _within(LimitName.OFFSET_SIGMA, _worst(sigma.offset_a_mA, sigma.offset_b_mA), None,
                limits.max_offset_sigma_mA, "mA"),
        _within(LimitName.GAIN_SIGMA, _worst(sigma.gain_a, sigma.gain_b), None,
                limits.max_gain_sigma, _GAIN),
    ]
    r2 = worst_r_squared(estimate)
    if r2 is None:
        checks.append(LimitCheck(LimitName.FIT_R2, None, limits.min_fit_r_squared, None, "", None,
                                 "no fit had points to spare: nothing to judge it by"))
    elif r2 == math.inf:
        checks.append(LimitCheck(LimitName.FIT_R2, None, limits.min_fit_r_squared, None, "", True,
                                 "every fit within the noise"))
    else:
        checks.append(_within(LimitName.FIT_R2, r2, limits.min_fit_r_squared, None, ""))
    return tuple(checks)


def clipping_check(clipped: int, received: int, *, remeasured: int = 0,
                   left_out: int = 0) -> LimitCheck:
    """How many measured samples sat at the sensor's full scale, and what the station did
    about it: never judged (a clipped hold is measured again or left out, as the recipe
    allows, and the estimate is judged on its own), always shown, so that no estimate
    comes silently from clipped holds."""
    note = (f"{clipped} of {received} samples at full scale, left out of the fits" if clipped
            else "no sample at full scale")
    if remeasured:
        note += f"; {remeasured} hold(s) measured again nearer the centre"
    if left_out:
        note += f"; {left_out} point(s) left out"
    return LimitCheck(LimitName.CLIPPED, float(clipped), None, None, "samples", None, note)


def unsupported(reason: str) -> LimitCheck:
    """The unit's response supported no estimate: a failed unit, with the reason."""
    return LimitCheck(LimitName.ESTIMATE, None, None, None, "", False, reason)


def reduction_db(before: float, after: float) -> float:
    """How much quieter one harmonic got, in dB of amplitude."""
    if after <= 0.0:
        return math.inf
    if before <= 0.0:
        return -math.inf
    return 20.0 * math.log10(before / after)


RIPPLE_LIMITS = frozenset({LimitName.H1_AFTER, LimitName.H2_AFTER, LimitName.H1_REDUCTION,
                           LimitName.H2_REDUCTION})
"""The limits ``ripple_checks`` judges: what a verification alone can fail."""


def ripple_checks(limits: Limits, before: Ripple | None, after: Ripple, hidden: float = 0.0
                  ) -> tuple[LimitCheck, ...]:
    """Limits judged on the verification run, against the baseline where one exists.

    ``hidden`` is what the verification's samples over the sensor's rail may hide of
    each harmonic (``hidden_by_clipping``): the unit is judged on the most it could
    have, because a waveform that peaks over the rail at the same phase in every
    period can carry a harmonic the fit never sees (development seed 1742693704 read
    H1 0.014 m/s² where the plant has 0.42).

    The reduction is judged per harmonic, and only for a harmonic that was
    outside its after-limit to begin with: a harmonic already quiet cannot be
    asked to get much quieter (it would fail for the noise floor's sake), and
    a 2nd harmonic at its irreducible floor must not hide a 1st that the
    offsets silenced.
    """
    checks = [
        _within(LimitName.H1_AFTER, after.h1 + hidden, None, limits.max_h1_after_mps2, _MPS2),
        _within(LimitName.H2_AFTER, after.h2 + hidden, None, limits.max_h2_after_mps2, _MPS2),
    ]
    if hidden:
        note = (f"{after.h1:.3g} and {after.h2:.3g} m/s² measured, and up to {hidden:.3g} "
                "more in samples over the sensor's rail")
        checks = [replace(c, note=note) for c in checks]
    pairs = (
        (LimitName.H1_REDUCTION, before.h1 if before else None, after.h1,
         limits.max_h1_after_mps2),
        (LimitName.H2_REDUCTION, before.h2 if before else None, after.h2,
         limits.max_h2_after_mps2),
    )
    for name, was, measured, quiet in pairs:
        now = measured + hidden
        low = limits.min_reduction_db
        if was is None:
            checks.append(LimitCheck(name, None, low, None, "dB", None,
                                     "no baseline was measured"))
        elif was <= quiet:
            checks.append(LimitCheck(name, reduction_db(was, now), low, None, "dB", None,
                                     "within its after-limit before calibration"))
        else:
            checks.append(_within(name, reduction_db(was, now), low, None, "dB"))
    return tuple(checks)


def verdict_for(checks: Iterable[LimitCheck]) -> Verdict:
    return Verdict.FAIL if any(c.passed is False for c in checks) else Verdict.PASS


def summary(checks: Sequence[LimitCheck]) -> str:
    """One line naming what failed, for the record's reason and the operator's banner."""
    failed = [c for c in checks if c.passed is False]
    if not failed:
        return "all limits met"
    parts = []
    for c in failed:
        if c.value is None:
            parts.append(f"{c.name}: {c.note}")
            continue
        # The bound it broke; a NaN breaks both, so name whichever exists.
        above = c.high is not None and not c.value <= c.high
        bound = c.high if above or c.low is None else c.low
        unit = f" {c.unit}" if c.unit else ""
        parts.append(f"{c.name} = {c.value:.4g}{unit} (limit {bound:g})")
    return "failed " + "; ".join(parts)


def drift_warnings(limits: Limits, previous: Trims, new: Trims) -> list[str]:
    """Field service: how far the trims moved since the unit's last calibration."""
    warnings: list[str] = []
    for name, old, now, bound, unit in (
        ("offset A", previous.offset_a_mA, new.offset_a_mA, limits.max_drift_offset_mA, "mA"),
        ("offset B", previous.offset_b_mA, new.offset_b_mA, limits.max_drift_offset_mA, "mA"),
        ("gain A", previous.gain_a, new.gain_a, limits.max_drift_gain, ""),
        ("gain B", previous.gain_b, new.gain_b, limits.max_drift_gain, ""),
    ):
        drift = now - old
        if abs(drift) > bound:
            warnings.append(
                f"{name} drifted by {drift:+.0f}{unit and ' ' + unit} since the last calibration "
                f"(from {old:.0f} to {now:.0f}; the recipe warns past {bound:g})"
            )
    return warnings


def drift(previous: Trims, new: Trims) -> Trims:
    """New minus previous trims, per trim."""
    return Trims(
        new.offset_a_mA - previous.offset_a_mA,
        new.offset_b_mA - previous.offset_b_mA,
        new.gain_a - previous.gain_a,
        new.gain_b - previous.gain_b,
    )
