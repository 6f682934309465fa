"""Cpk matches the textbook figures that QA will check it against by hand."""

from __future__ import annotations

import math

import pytest

from station.qa import Capability, capability

VALUES = (1.0, 2.0, 3.0, 4.0, 5.0)
# By hand: mean 3; squared deviations 4+1+0+1+4 = 10; s² = 10/(5-1) = 2.5.
SIGMA = math.sqrt(2.5)


def test_two_sided_cpk_is_the_nearer_limit() -> None:
    result = capability(VALUES, 0.0, 10.0)
    assert (result.n, result.mean, result.low, result.high) == (5, 3.0, 0.0, 10.0)
    assert result.std == pytest.approx(SIGMA)
    # Upper side (10-3)/(3s) = 1.4757, lower side (3-0)/(3s) = 0.6325: the lower wins.
    assert result.cpk == pytest.approx(0.632455532)


def test_upper_limit_only_uses_the_upper_side() -> None:
    assert capability(VALUES, None, 10.0).cpk == pytest.approx(1.475729575)


def test_lower_limit_only_uses_the_lower_side() -> None:
    assert capability(VALUES, 0.0, None).cpk == pytest.approx(0.632455532)


def test_centred_process_has_cpk_equal_to_cp() -> None:
    # Cp = (high - low) / 6s = 6 / (6 * sqrt(2.5)).
    assert capability(VALUES, 0.0, 6.0).cpk == pytest.approx(6.0 / (6.0 * SIGMA))


def test_mean_outside_the_limits_gives_negative_cpk() -> None:
    # mean 12, s = 1: (10 - 12) / 3.
    assert capability([11.0, 12.0, 13.0], 0.0, 10.0).cpk == pytest.approx(-2.0 / 3.0)


def test_no_limits_still_reports_mean_and_spread_without_cpk() -> None:
    result = capability(VALUES, None, None)
    assert result.cpk is None
    assert result.mean == 3.0
    assert result.std == pytest.approx(SIGMA)


def test_one_value_has_no_spread_and_no_cpk() -> None:
    result = capability([4.0], 0.0, 10.0)
    assert (result.n, result.mean, result.cpk) == (1, 4.0, None)
    assert math.isnan(result.std)


def test_no_values_give_no_cpk() -> None:
    result = capability([], 0.0, 10.0)
    assert (result.n, result.cpk) == (0, None)
    assert math.isnan(result.mean)


def test_identical_values_give_no_cpk_rather_than_infinity() -> None:
    assert capability([2.0, 2.0, 2.0], 0.0, 10.0) == Capability(3, 2.0, 0.0, 0.0, 10.0, None)


def test_non_finite_values_are_refused() -> None:
    with pytest.raises(ValueError, match="finite"):
        capability([1.0, math.nan, 2.0], 0.0, 10.0)


def test_crossed_limits_are_refused() -> None:
    with pytest.raises(ValueError, match="above"):
        capability(VALUES, 10.0, 0.0)
