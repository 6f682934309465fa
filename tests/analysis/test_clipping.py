"""What samples over the sensor's rail may hide of a hold's harmonics."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis.clipping import clipped_runs, hidden_by_clipping
from station.analysis.harmonics import Harmonics, demodulate

SAMPLES_PER_PERIOD = 50  # 20 Hz at the SYNC's 1 kHz: the same phases in every period
RAIL = 150.0


def _waveform(periods: int = 8, *, peak: float = 88.0) -> tuple[NDArray[np.float64], ...]:
    """A small H1 under strong higher orders whose peaks cross the rail at the same
    phases in every period, as flux harmonics and current distortion put them."""
    n = np.arange(periods * SAMPLES_PER_PERIOD)
    angle = 2.0 * math.pi * n / SAMPLES_PER_PERIOD
    # Order 21 is beyond the orders fitted, as a sharp peak's content is.
    x = (0.05 * np.cos(angle + 0.7) + peak * np.cos(13 * angle)
         + 0.8 * peak * np.cos(21 * angle + 0.4))
    return x, angle


def _read(x: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.int64],
                                          NDArray[np.bool_]]:
    """As the sensor gives it: counts at the rail where the waveform is over it, and the
    acceleration the analysis sees (NaN there)."""
    at_rail = np.abs(x) >= RAIL
    counts = np.where(at_rail, np.sign(x) * 32767, np.round(x / RAIL * 32767)).astype(np.int64)
    signal = np.where(at_rail, np.nan, x)
    return signal, counts, at_rail


def test_a_peak_over_the_rail_may_hide_at_least_what_it_moves_the_harmonics_by() -> None:
    x, angle = _waveform()
    signal, counts, at_rail = _read(x)
    assert 0 < at_rail.mean() < 0.1
    whole = demodulate(x, angle, SAMPLES_PER_PERIOD, orders=16)
    seen = demodulate(signal, angle, SAMPLES_PER_PERIOD, orders=16)
    hidden = hidden_by_clipping(signal, counts, at_rail, RAIL, imputed=_imputed(seen, signal))
    # The missing phases decide the small harmonic, and what may be hidden says so.
    assert abs(seen.h(1) - whole.h(1)) > 10 * abs(whole.h(1))
    for order in (1, 2):
        assert abs(seen.h(order) - whole.h(order)) <= hidden


def _imputed(h: Harmonics, signal: NDArray[np.float64]) -> NDArray[np.float64]:
    model = np.full(signal.size, np.nan)
    assert h.imputed is not None
    model[np.isnan(signal)] = h.imputed
    return model


def test_a_hold_that_never_reaches_the_rail_hides_nothing() -> None:
    x, _ = _waveform(peak=60.0)
    signal, counts, at_rail = _read(x)
    assert not at_rail.any()
    assert hidden_by_clipping(signal, counts, at_rail, RAIL, imputed=signal) == 0.0


def test_a_run_whose_neighbours_were_lost_takes_the_steepest_step_of_the_hold() -> None:
    x, _ = _waveform()
    signal, counts, at_rail = _read(x)
    put = np.where(at_rail, np.sign(x) * RAIL, np.nan)  # as if the fit had put the rail there
    (first, last), *_ = clipped_runs(at_rail)
    known = hidden_by_clipping(signal, counts, at_rail, RAIL, imputed=put)
    lost = signal.copy()
    lost[first - 1] = lost[last] = np.nan  # frames lost beside the run
    unknown = hidden_by_clipping(lost, counts, at_rail, RAIL, imputed=put)
    assert unknown >= known  # no slope is known there: the steepest the hold shows
    steepest = max(float(np.nanmax(np.abs(np.diff(lost)))), 2 * RAIL)
    width = last - first
    assert unknown <= known + steepest * 2.0 * width * (width + 1) / 4.0 / x.size


@pytest.mark.parametrize(("flags", "runs"), [
    ([0, 0, 0], []),
    ([1, 1, 0, 1], [(0, 2), (3, 4)]),
    ([0, 1, 1, 1, 0], [(1, 4)]),
])
def test_clipped_runs_are_the_stretches_at_the_rail(flags: list[int],
                                                    runs: list[tuple[int, int]]) -> None:
    assert clipped_runs(np.array(flags, dtype=bool)) == runs
