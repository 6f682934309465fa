"""Where the phasors look for the run's clock (station.analysis.phasor_clock)."""

from __future__ import annotations

import pytest

from station.analysis.phasor_clock import CLOCK_RANGE, search_range
from station.analysis.sampling import RateObservation

PPM = 1e-6


def test_a_clock_the_holds_timed_is_refined_near_it_however_far_off_it_runs() -> None:
    # An RC oscillator 2 % off: the holds see it, and the phasors look only near it.
    low, high = search_range(RateObservation(-21_000 * PPM, 500 * PPM))
    assert low < -21_000 * PPM < high
    assert (low, high) == pytest.approx((-23_000 * PPM, -19_000 * PPM))


def test_a_clock_the_holds_could_not_tell_from_zero_is_looked_for_within_the_range() -> None:
    # A belt's ringing holds: a median of 300 ± 400 ppm says little, and the range bounds it.
    assert search_range(RateObservation(300 * PPM, 400 * PPM)) == pytest.approx(
        (-CLOCK_RANGE, CLOCK_RANGE))
    # Quieter holds narrow it, zero always inside.
    low, high = search_range(RateObservation(50 * PPM, 20 * PPM))
    assert (low, high) == pytest.approx((-50 * PPM, 150 * PPM))
    assert low < 0.0 < high
