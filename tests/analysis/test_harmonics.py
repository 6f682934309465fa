"""Harmonic phasors of a segment (station.analysis.harmonics.demodulate), on synthetic arrays."""

from __future__ import annotations

import math

import numpy as np
import pytest
from numpy.typing import NDArray
from scipy.signal import lfilter

from station.analysis.harmonics import (
    DEFAULT_ORDERS,
    JOINT_ORDERS,
    SampleClock,
    SteadyProjection,
    demodulate,
    slow_variance,
)

SPP = 50.0  # samples per electrical period: 20 Hz at a 1 ms SYNC
PERIODS = 12
DC = 9.5
# Order -> phasor A·e^{jφ} of A·cos(kθ + φ): a typical ripple with a strong 4th (detent).
CONTENT: dict[int, complex] = {
    1: 0.8 * np.exp(0.4j),
    2: 0.25 * np.exp(-1.2j),
    3: 0.05 * np.exp(2.0j),
    4: 0.4 * np.exp(-2.8j),
    6: 0.02 * np.exp(0.1j),
}


def _angle(samples: int, spp: float = SPP, start: float = 0.7) -> NDArray[np.float64]:
    """Electrical angle as a segment gives it: wrapped into [0, 2π)."""
    phase = start + 2 * math.pi * np.arange(samples, dtype=np.float64) / spp
    return np.mod(phase, 2 * math.pi)


def _signal(angle: NDArray[np.float64], content: dict[int, complex]) -> NDArray[np.float64]:
    out = np.full(angle.shape, DC)
    for k, h in content.items():
        out += abs(h) * np.cos(k * angle + np.angle(h))
    return out


def _drop(signal: NDArray[np.float64], fraction: float, seed: int) -> NDArray[np.float64]:
    """Lose a random ``fraction`` of the samples, as a lossy logger and clipping do."""
    rng = np.random.default_rng(seed)
    lost = signal.copy()
    lost[rng.choice(signal.size, round(fraction * signal.size), replace=False)] = np.nan
    return lost


def test_phasors_of_a_multi_harmonic_signal_are_exact() -> None:
    angle = _angle(round(PERIODS * SPP))
    h = demodulate(_signal(angle, CONTENT), angle, SPP)
    assert h.phasors.shape == (DEFAULT_ORDERS,)
    for k in range(1, DEFAULT_ORDERS + 1):
        assert h.h(k) == pytest.approx(CONTENT.get(k, 0j), abs=1e-12)
    assert h.dc == pytest.approx(DC, abs=1e-12)
    assert h.residual_rms < 1e-12
    assert (h.samples_used, h.samples_missing) == (angle.size, 0)


def test_phasors_stay_exact_with_ten_percent_of_samples_missing() -> None:
    angle = _angle(round(PERIODS * SPP))
    signal = _drop(_signal(angle, CONTENT), 0.10, seed=4)
    h = demodulate(signal, angle, SPP)
    for k in range(1, DEFAULT_ORDERS + 1):
        assert h.h(k) == pytest.approx(CONTENT.get(k, 0j), abs=1e-10)
    assert h.samples_missing == round(0.10 * angle.size)
    assert h.samples_used + h.samples_missing == angle.size


def test_a_fit_of_few_orders_is_exact_when_the_signal_has_no_higher_orders() -> None:
    """Plain correlation over the holes lost samples leave would mix orders; the
    least-squares fit does not, as long as nothing above the fitted orders is there."""
    content = {1: CONTENT[1], 2: CONTENT[2]}
    angle = _angle(round(PERIODS * SPP))
    signal = _drop(_signal(angle, content), 0.10, seed=5)
    h = demodulate(signal, angle, SPP, orders=2)
    assert h.phasors.shape == (2,)
    assert h.h(1) == pytest.approx(content[1], abs=1e-12)
    assert h.h(2) == pytest.approx(content[2], abs=1e-12)
    # Correlation over the same holes would be off by far more than that.
    ok = ~np.isnan(signal)
    naive = 2 * np.mean(signal[ok] * np.exp(-1j * angle[ok]))
    assert abs(naive - content[1]) > 1e-3


def test_a_partial_last_period_does_not_bias_the_phasors() -> None:
    angle = _angle(round(PERIODS * SPP) + 17)
    h = demodulate(_signal(angle, CONTENT), angle, SPP)
    assert h.h(1) == pytest.approx(CONTENT[1], abs=1e-12)
    assert h.h(4) == pytest.approx(CONTENT[4], abs=1e-12)


def test_orders_at_or_above_nyquist_are_not_fitted() -> None:
    """Five samples per period resolve orders 1 and 2 only; the rest would alias."""
    spp = 5.0
    content = {1: CONTENT[1], 2: CONTENT[2]}
    angle = _angle(200, spp=spp)
    h = demodulate(_signal(angle, content), angle, spp)
    assert h.h(1) == pytest.approx(content[1], abs=1e-12)
    assert h.h(2) == pytest.approx(content[2], abs=1e-12)
    assert np.isnan(h.phasors[2:]).all()
    assert np.isnan(h.variance[2:]).all()
    assert np.isfinite(h.variance[:2]).all()


def test_exactly_two_samples_per_order_period_is_not_fitted() -> None:
    """At four samples per period the 2nd order sits on Nyquist: its sine is never sampled."""
    spp = 4.0
    angle = _angle(200, spp=spp)
    h = demodulate(_signal(angle, {1: CONTENT[1]}), angle, spp)
    assert h.h(1) == pytest.approx(CONTENT[1], abs=1e-12)
    assert np.isnan(h.phasors[1:]).all()


def _noise_trial(
    seed: int, noise: NDArray[np.float64], angle: NDArray[np.float64]
) -> tuple[NDArray[np.complex128], NDArray[np.float64]]:
    signal = _drop(_signal(angle, CONTENT) + noise, 0.10, seed)
    h = demodulate(signal, angle, SPP)
    errors = h.phasors[:3] - np.array([CONTENT.get(k, 0j) for k in (1, 2, 3)])
    return errors, h.variance[:3]


def _ar1(rng: np.random.Generator, size: int, pole: float, sigma: float) -> NDArray[np.float64]:
    """Red noise (a slow drift, a ringing mode's skirt): more power at low orders."""
    white = rng.normal(0.0, sigma * math.sqrt(1 - pole**2), size)
    start = rng.normal(0.0, sigma)
    filtered = lfilter([1.0], [1.0, -pole], white, zi=[pole * start])[0]
    return np.asarray(filtered, dtype=np.float64)


@pytest.mark.parametrize("pole", [0.0, 0.8])
def test_reported_variance_matches_the_scatter_over_noise_seeds(pole: float) -> None:
    """E|Ĥ_k − H_k|² over many seeds, white and coloured noise, with 10 % lost."""
    angle = _angle(round(20 * SPP))
    rng = np.random.default_rng(11)
    trials = 300
    errors = np.empty((trials, 3), dtype=np.complex128)
    reported = np.empty((trials, 3))
    for t in range(trials):
        errors[t], reported[t] = _noise_trial(t, _ar1(rng, angle.size, pole, 0.05), angle)
    empirical = np.mean(np.abs(errors) ** 2, axis=0)
    ratio = np.mean(reported, axis=0) / empirical
    assert np.all(ratio > 0.7) and np.all(ratio < 1.3), ratio
    # Unbiased phasors: the mean error is a small fraction of the scatter.
    assert np.all(np.abs(errors.mean(axis=0)) < 4 * np.sqrt(empirical / trials))


def test_a_transient_at_known_poles_is_fitted_out_and_costs_precision() -> None:
    """A mode at 37 Hz (SPP 50 at 1 kHz: between orders 1 and 2) decaying over the
    segment, from a change 40 samples before its first."""
    angle = _angle(round(6 * SPP))
    pole = complex(-0.004, 2 * math.pi * 37.0 / 1000.0)
    t = 40.0 + np.arange(angle.size)
    ring = 0.6 * np.exp(pole.real * t) * np.cos(pole.imag * t + 0.3)
    signal = _drop(_signal(angle, CONTENT) + ring, 0.10, 3)
    fitted = demodulate(signal, angle, SPP, decays=(pole,), decay_from=40.0)
    for k in range(1, DEFAULT_ORDERS + 1):
        assert fitted.h(k) == pytest.approx(CONTENT.get(k, 0j), abs=1e-9)
    ignored = demodulate(signal, angle, SPP)
    assert abs(ignored.h(2) - CONTENT[2]) > 0.01
    # The harmonics share precision with the decay's columns: their variance per unit of
    # sample noise grows, most at the orders next to the mode.
    clean = demodulate(_drop(_signal(angle, CONTENT), 0.10, 3), angle, SPP)
    assert clean.unit_variance is not None and fitted.unit_variance is not None
    growth = fitted.unit_variance / clean.unit_variance
    assert np.all(growth >= 1.0 - 1e-9)
    assert np.argmax(growth) == 1 and growth.max() > 1.02  # order 2, at 40 Hz


def test_a_taper_keeps_a_ring_far_from_the_low_orders_out_of_them() -> None:
    """A verification's hold: 4 periods, a mode at 99 Hz (near order 5) still decaying from
    the start, 20 m/s² against a few hundredths of H1 (development seed 1552235132)."""
    angle = _angle(round(4 * SPP))
    t = np.arange(angle.size)
    ring = 20.0 * np.exp(-0.01 * t) * np.cos(2 * math.pi * 99.0 / 1000.0 * t + 0.4)
    content = {1: 0.03 + 0.01j, 2: -0.02j, 4: 30.0 + 5j, 5: 3.0}
    signal = _signal(angle, content) + ring
    flat = demodulate(signal, angle, SPP)
    tapered = demodulate(signal, angle, SPP, taper=True)
    assert abs(flat.h(1) - content[1]) > 0.02
    for k in (1, 2):
        assert abs(tapered.h(k) - content[k]) < 0.005
    # Without the ring the taper changes nothing but the noise it passes.
    clean = demodulate(_signal(angle, content), angle, SPP, taper=True)
    assert clean.h(1) == pytest.approx(content[1], abs=1e-9)


def test_a_tapers_reported_variance_matches_its_scatter_over_noise_seeds() -> None:
    angle = _angle(round(4 * SPP))
    rng = np.random.default_rng(5)
    trials = 400
    errors = np.empty((trials, 2), dtype=np.complex128)
    reported = np.empty((trials, 2))
    flat = np.empty(trials)
    for i in range(trials):
        signal = _signal(angle, CONTENT) + rng.normal(0.0, 0.05, angle.size)
        h = demodulate(signal, angle, SPP, taper=True)
        errors[i] = [h.h(1) - CONTENT[1], h.h(2) - CONTENT[2]]
        reported[i] = h.variance[:2]
        flat[i] = demodulate(signal, angle, SPP).variance[0]
    # Never below the scatter, and above it by what a 4-period hold's per-period scatter
    # adds to any window's figure (1.28 for the flat one here), not by more.
    ratio = np.mean(reported, axis=0) / np.mean(np.abs(errors) ** 2, axis=0)
    assert np.all(ratio > 0.9) and np.all(ratio < 1.6), ratio
    # What the taper costs: about half as much variance again as the flat window's.
    assert 1.2 < np.mean(reported[:, 0]) / np.mean(flat) < 2.2


def test_a_ring_the_window_cannot_tell_from_the_harmonics_is_left_out_not_split_from_them(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """One period of a mode decaying in seconds, with its sidebands at ± one and two
    orders: over one period these are together the harmonics times a ramp. Fitted anyway,
    the two split the signal into huge opposite parts; left out, the phasors stay what the
    window shows (the ring's own share of it, at most)."""
    angle = _angle(round(SPP))
    turn = 2 * math.pi / SPP
    pole = complex(-1e-3, 2 * math.pi * 37.0 / 1000.0)
    poles = (pole, *(pole + 1j * k * turn for k in (1, -1, 2, -2)))
    t = 300.0 + np.arange(angle.size)
    ring = 0.05 * np.exp(pole.real * t) * np.cos(pole.imag * t)
    noise = np.random.default_rng(5).normal(0.0, 0.01, angle.size)
    signal = _signal(angle, CONTENT) + ring + noise

    def worst() -> float:
        fitted = demodulate(signal, angle, SPP, decays=poles, decay_from=300.0)
        return max(abs(fitted.h(k) - CONTENT.get(k, 0j)) for k in range(1, DEFAULT_ORDERS + 1))

    assert worst() < 0.2
    monkeypatch.setattr("station.analysis.harmonics.SEPARABLE", 0.0)
    assert worst() > 1.0


@pytest.mark.parametrize(
    "case", ["two modes", "one mode twice", "a mode on order 2", "two modes, one period"]
)
def test_a_pole_search_is_given_the_least_squares_residual_of_its_decays(case: str) -> None:
    """The search's residual is what lstsq leaves, also where the decays' columns are
    not independent: a pole given twice, an undamped one on a harmonic (nothing is left
    of it once the harmonics are projected out), or sidebands one period cannot tell
    apart. A plain QR projection would add a direction of rounding noise there."""
    periods = 1 if case == "two modes, one period" else 6
    angle = _angle(round(periods * SPP))
    signal = _drop(_signal(angle, CONTENT), 0.10, 3)
    t = 40.0 + np.arange(angle.size)
    first = complex(-0.004, 2 * math.pi * 37.0 / 1000.0)
    second = complex(-0.01, 2 * math.pi * 61.0 / 1000.0)
    on_order_2 = complex(0.0, 2 * math.pi * 2 / SPP)
    poles = {
        "two modes": (first, second),
        "one mode twice": (first, first),
        "a mode on order 2": (first, on_order_2),
        "two modes, one period": (first, first + 1j * 2 * math.pi / SPP),
    }[case]
    for pole, amplitude in zip(poles, (0.6, 0.2), strict=True):
        signal += amplitude * np.exp(pole.real * t) * np.cos(pole.imag * t + 0.3)
    signal += np.random.default_rng(11).normal(0.0, 0.01, signal.size)
    window = SteadyProjection.of(signal, angle, SPP, decay_from=40.0)

    ok = ~np.isnan(signal)
    orders = min(JOINT_ORDERS, math.floor(SPP / 2 - 1e-9))  # what demodulate fits
    harmonics = [np.ones(angle.size)] + [
        f(k * angle) for k in range(1, orders + 1) for f in (np.cos, np.sin)
    ]
    decays = [
        np.exp(p.real * t) * f(p.imag * t) for p in poles for f in (np.cos, np.sin)
    ]
    design = np.column_stack(harmonics + decays)[ok]
    coef, *_ = np.linalg.lstsq(design, signal[ok], rcond=None)
    expected = signal[ok] - design @ coef
    np.testing.assert_allclose(window.residual(poles), expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("noise", [0.0, 0.01, 0.3])
def test_a_pole_searchs_slopes_are_those_of_its_residual(noise: float) -> None:
    """``DecayFit.slopes`` against central differences of the residual, with
    samples missing, a mode and its sideband swept, a real pole beside them, and noise
    from none to far above the ringing: the variable projection's derivative has a term
    as large as the residual, which an approximation that drops it gets wrong exactly
    where a belt's holds are (ringing near the noise)."""
    angle = _angle(round(8 * SPP))
    signal = _drop(_signal(angle, CONTENT), 0.10, 5)
    ok = ~np.isnan(signal)
    t = 40.0 + np.arange(angle.size)
    turn = 2j * math.pi / SPP

    def decays(x: NDArray[np.float64]) -> tuple[list[complex], list[float]]:
        """A mode (rate and frequency scaled by e^x), its sideband, a real pole; the
        mode's sweep moved by x[2]."""
        mode = complex(-0.004 * math.exp(x[0]), 2 * math.pi * 37.0 / 1000.0 * math.exp(x[1]))
        sweep = 2e-7 * (1.0 + x[2])
        return [mode, mode + turn, complex(-0.02 * math.exp(x[0]), 0.0)], [sweep, sweep, 0.0]

    truth = np.array([0.1, -0.01, 0.5])
    poles, sweeps = decays(truth)
    middle = 0.5 * (t[ok][0] + t[ok][-1])
    for pole, sweep, amplitude in zip(poles, sweeps, (0.6, 0.2, 0.4), strict=True):
        signal += amplitude * np.exp(pole.real * t) * np.cos(
            pole.imag * t + 0.5 * sweep * (t - middle) ** 2 + 0.3)
    signal += np.random.default_rng(12).normal(0.0, noise, signal.size)
    window = SteadyProjection.of(signal, angle, SPP, decay_from=40.0)

    def tangents(x: NDArray[np.float64]) -> NDArray[np.float64]:
        out = []
        for j in range(x.size):
            step = np.eye(x.size)[j] * 1e-6
            ends = [np.array([[p.real, p.imag, c] for p, c in zip(*decays(x + sign * step),
                                                                  strict=True)])
                    for sign in (1.0, -1.0)]
            out.append((ends[0] - ends[1]) / 2e-6)
        return np.array(out)

    for x in (truth, np.zeros(3), np.array([0.3, 0.02, -0.4])):
        slopes = window.fit(*decays(x)).slopes(tangents(x))
        assert slopes is not None
        step = 1e-6
        differenced = np.column_stack([
            (window.residual(*decays(x + step * e)) - window.residual(*decays(x - step * e)))
            / (2 * step) for e in np.eye(3)])
        np.testing.assert_allclose(slopes, differenced, rtol=0,
                                   atol=1e-5 * np.abs(differenced).max())
    # Columns the window cannot tell apart: no slope, the caller differences the residual.
    mode = poles[0]
    assert window.fit([mode, mode], [0.0, 0.0]).slopes(np.zeros((1, 2, 3))) is None


@pytest.mark.parametrize("samples", [0, 1, 2, 17, 4000])
def test_a_clocks_turns_are_the_exponentials_of_its_sample_times(samples: int) -> None:
    """Over holds of seconds, with samples missing and the decay's change before the
    window, at rings up to the Nyquist rate: as close to e^{jωt} as ωt itself is known."""
    rng = np.random.default_rng(samples)
    present = np.sort(rng.choice(int(1.1 * samples) + 1, samples, replace=False))
    clock = SampleClock.of(present, 37.0)
    t = present + 37.0
    np.testing.assert_array_equal(clock.times, t)
    for omega in (2 * math.pi * 37.0 / 1000.0, 0.9 * math.pi, -0.3):
        # ωt is rounded to its own last bit, which at the end of 4000 samples is 2e-12.
        known = 4 * np.finfo(float).eps * abs(omega) * float(t.max(initial=1.0))
        (table,) = clock.tables(np.array([omega]))
        np.testing.assert_allclose(clock.turns(table), np.exp(1j * omega * t), rtol=0,
                                   atol=known)


def test_mismatched_shapes_and_too_few_samples_are_refused() -> None:
    angle = _angle(100)
    with pytest.raises(ValueError, match="must match"):
        demodulate(np.zeros(99), angle, SPP)
    few = np.full(angle.size, np.nan)
    few[:10] = 1.0
    with pytest.raises(ValueError, match="cannot determine"):
        demodulate(few, angle, SPP)


@pytest.mark.parametrize("lost", [0.0, 0.05])
def test_tonal_ripple_above_the_fitted_orders_is_not_counted_as_noise(lost: float) -> None:
    """A chain mode high in the band carries orders beyond ``JOINT_ORDERS``: they are part
    of the periodic motion, not of the sensor's noise that the phasors' σ comes from."""
    spp = 83.3  # 12 Hz at a 1 ms SYNC: orders up to 41 are resolved
    angle = _angle(round(8 * spp), spp)
    sigma = 0.07
    high = {k: 0.6 * np.exp(0.3j * k) for k in range(JOINT_ORDERS + 1, JOINT_ORDERS + 6)}
    noise = np.random.default_rng(11).normal(0.0, sigma, angle.size)
    signal = _drop(_signal(angle, CONTENT | high) + noise, lost, seed=3)
    h = demodulate(signal, angle, spp, white_noise=True)
    assert h.noise_variance == pytest.approx(sigma**2, rel=0.15)
    # What the reported orders keep from the 16 fitted ones is not white: far above σ².
    assert h.residual_rms**2 > 20 * sigma**2


def test_a_segment_too_short_for_every_order_finds_its_noise_with_the_orders_it_can_fit(
) -> None:
    spp = 166.7  # 6 Hz: 83 orders resolved, more than one period's samples can fit
    angle = _angle(round(1.2 * spp), spp)
    sigma = 0.05
    noise = np.random.default_rng(12).normal(0.0, sigma, angle.size)
    h = demodulate(_signal(angle, CONTENT) + noise, angle, spp, white_noise=True)
    assert math.isfinite(h.noise_variance)
    assert h.noise_variance == pytest.approx(sigma**2, rel=0.3)


def _turning(angle: NDArray[np.float64], depth: float) -> NDArray[np.float64]:
    """``CONTENT`` modulated once per mechanical revolution (50 electrical periods), as an
    eccentric airgap turns with the rotor: the hold sees a quarter of a revolution."""
    periods = np.unwrap(angle) / (2 * math.pi)
    return DC + (1.0 + depth * np.sin(2 * math.pi * periods / 50.0 + 0.3)) * (
        _signal(angle, CONTENT) - DC)


def test_harmonics_turning_slowly_through_a_hold_leave_only_the_noise() -> None:
    rng = np.random.default_rng(5)
    angle = _angle(round(12.5 * SPP))
    sigma = 0.002
    signal = _turning(angle, 0.3) + rng.normal(0.0, sigma, angle.size)
    held = demodulate(signal, angle, SPP, white_noise=True)
    assert held.noise_variance > 30 * sigma**2  # what a hold's mean harmonics leave
    assert slow_variance(signal, angle, SPP, DEFAULT_ORDERS) < 1.5 * sigma**2


def test_motion_that_is_not_periodic_is_left_when_harmonics_may_change_slowly() -> None:
    rng = np.random.default_rng(6)
    angle = _angle(round(3 * SPP))
    sigma = 0.002
    # A rotor nearly out of step wanders: a swing with no period, a tenth of the ripple's
    # size, its spectrum spread over the orders (one tone close to an order would be that
    # order turning through a short hold).
    swing = lfilter([0.3], [1.0, -0.7], rng.normal(0.0, 0.1, angle.size))
    signal = _signal(angle, CONTENT) + swing + rng.normal(0.0, sigma, angle.size)
    assert slow_variance(signal, angle, SPP, DEFAULT_ORDERS) > 30 * sigma**2
    assert slow_variance(_drop(signal, 0.1, seed=7), angle, SPP,
                         DEFAULT_ORDERS) > 30 * sigma**2


def test_a_hold_too_short_for_slowly_changing_harmonics_gives_no_figure() -> None:
    angle = _angle(round(1.5 * SPP))
    assert math.isnan(slow_variance(_signal(angle, CONTENT), angle, SPP, DEFAULT_ORDERS))
