"""Synchronous demodulation against signals whose harmonics are known."""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.dsp.demod import harmonic_phasors


def _angle(periods: int = 5, per_period: int = 50) -> np.ndarray:
    return np.arange(periods * per_period) * 2 * math.pi / per_period + 0.3


def test_amplitude_and_phase_of_each_order_are_recovered() -> None:
    angle = _angle()
    signal = 1.5 + 0.8 * np.cos(angle + 0.4) + 0.25 * np.cos(2 * angle - 1.2) + 0.1 * np.sin(
        4 * angle)
    h = harmonic_phasors(signal, angle, [1, 2, 3, 4])
    np.testing.assert_allclose(h[0], 0.8 * np.exp(0.4j), atol=1e-12)
    np.testing.assert_allclose(h[1], 0.25 * np.exp(-1.2j), atol=1e-12)
    assert abs(h[2]) < 1e-12
    np.testing.assert_allclose(h[3], 0.1 * np.exp(-0.5j * math.pi), atol=1e-12)


def test_order_zero_gives_twice_the_mean() -> None:
    angle = _angle()
    assert harmonic_phasors(np.full(angle.size, 2.0), angle, [0])[0] == pytest.approx(4.0)


def test_white_noise_averages_down_with_the_number_of_samples() -> None:
    rng = np.random.default_rng(0)
    angle = _angle(periods=400)
    noise = rng.normal(0.0, 1.0, angle.size)
    h = harmonic_phasors(0.05 * np.cos(angle) + noise, angle, [1])[0]
    # Each quadrature has σ = √(2/N); five of them is a generous bound.
    assert abs(h - 0.05) < 5 * math.sqrt(2 / angle.size)


def test_mismatched_or_empty_inputs_are_refused() -> None:
    with pytest.raises(ValueError, match="equally long"):
        harmonic_phasors(np.zeros(10), np.zeros(9), [1])
    with pytest.raises(ValueError, match="no samples"):
        harmonic_phasors(np.zeros(0), np.zeros(0), [1])
