"""The torque model against the paper's closed forms and against itself."""

from __future__ import annotations

import math

import numpy as np
import pytest

from station.core import Effect
from station.physics.motor import (
    FluxHarmonic,
    MotorParams,
    inductance_matrix,
    mutual_inductances,
    ripple_harmonic_magnitudes,
    torque,
    torque_closed_form,
    torque_components,
    torque_numerical,
)
from station.physics.params import derive_unit

PAPER_MOTOR = MotorParams()
"""Assumptions (10): no reluctance variation, no flux harmonics, no detent."""


def _every_effect_motor() -> MotorParams:
    return derive_unit("SN4711", effects=list(Effect)).motor


def _ripple_phasors(motor: MotorParams, *, I10: float, I20: float, I11: float, I21: float,
                    rho: float, samples: int = 720) -> np.ndarray:
    """Torque harmonics over one electrical period at constant electrical load angle ρ."""
    x = np.arange(samples) * 2 * math.pi / samples
    theta = (x - rho) / motor.rotor_teeth
    tau = torque(theta, I10 + I11 * np.cos(x), I20 + I21 * np.sin(x), motor)
    return np.fft.rfft(tau) * 2 / samples


def _h1_null_offsets(motor: MotorParams, amplitude_A: float, rho: float) -> np.ndarray:
    """Net phase offsets (A) that null the 1st torque harmonic: H1 is affine in them."""
    def h1(i10: float, i20: float) -> complex:
        return complex(_ripple_phasors(motor, I10=i10, I20=i20, I11=amplitude_A,
                                       I21=amplitude_A, rho=rho)[1])

    base = h1(0.0, 0.0)
    da = h1(0.01, 0.0) - base
    db = h1(0.0, 0.01) - base
    a = np.array([[da.real, db.real], [da.imag, db.imag]]) / 0.01
    return np.asarray(np.linalg.solve(a, -np.array([base.real, base.imag])))


def test_analytic_torque_equals_central_difference_of_the_inductance_matrix() -> None:
    motor = _every_effect_motor()
    rng = np.random.default_rng(1)
    theta = rng.uniform(-1.0, 1.0, 200)
    i_a = rng.uniform(-1.5, 1.5, 200)
    i_b = rng.uniform(-1.5, 1.5, 200)
    analytic = torque(theta, i_a, i_b, motor)
    numeric = torque_numerical(theta, i_a, i_b, motor)
    np.testing.assert_allclose(analytic, numeric, rtol=1e-6, atol=1e-8)


def test_torque_components_add_up_to_eq1() -> None:
    motor = _every_effect_motor()
    theta = np.linspace(0.0, 0.3, 50)
    pm, vr, cg = torque_components(theta, 0.7, -0.2, motor)
    np.testing.assert_allclose(pm + vr + cg, torque(theta, 0.7, -0.2, motor), rtol=1e-12)
    assert np.max(np.abs(vr)) > 0 and np.max(np.abs(cg)) > 0


def test_inductance_matrix_is_symmetric_positive_definite_at_every_angle() -> None:
    theta = np.linspace(0.0, 2 * math.pi / 50, 97)
    for motor in (PAPER_MOTOR, _every_effect_motor()):
        matrices = inductance_matrix(theta, motor)
        np.testing.assert_array_equal(matrices, np.swapaxes(matrices, -1, -2))
        assert np.all(np.linalg.eigvalsh(matrices) > 0)


def test_eq1_torque_equals_closed_form_16_under_assumptions_10() -> None:
    rng = np.random.default_rng(7)
    n = 500
    theta = rng.uniform(-math.pi, math.pi, n)
    theta_u = theta + rng.uniform(-0.05, 0.05, n)
    for _ in range(20):
        I10, I20 = rng.uniform(-0.5, 0.5, 2)
        I11, I21 = rng.uniform(0.5, 1.5, 2)
        x_u = PAPER_MOTOR.rotor_teeth * theta_u
        by_eq1 = torque(theta, I10 + I11 * np.cos(x_u), I20 + I21 * np.sin(x_u), PAPER_MOTOR)
        by_eq16 = torque_closed_form(theta, theta_u, PAPER_MOTOR, I10=I10, I20=I20, I11=I11,
                                     I21=I21)
        np.testing.assert_allclose(by_eq1, by_eq16, rtol=1e-9, atol=1e-12)


def test_closed_form_16_is_not_the_torque_once_flux_harmonics_exist() -> None:
    motor = _every_effect_motor()
    theta = np.linspace(0.0, 0.2, 100)
    x_u = motor.rotor_teeth * theta + 0.3
    by_eq1 = torque(theta, 0.1 + np.cos(x_u), np.sin(x_u), motor)
    by_eq16 = torque_closed_form(theta, x_u / motor.rotor_teeth, motor, I10=0.1, I20=0.0,
                                 I11=1.0, I21=1.0)
    assert np.max(np.abs(by_eq1 - by_eq16)) > 1e-3


@pytest.mark.parametrize("rho", [0.0, 0.4, -0.9])
def test_torque_ripple_harmonics_follow_eq17_and_eq18(rho: float) -> None:
    I10, I20, I11, I21 = 0.12, -0.055, 0.847, 1.153
    h = _ripple_phasors(PAPER_MOTOR, I10=I10, I20=I20, I11=I11, I21=I21, rho=rho)
    h1, h2 = ripple_harmonic_magnitudes(PAPER_MOTOR, I10, I20, I11, I21)
    assert abs(h[1]) == pytest.approx(h1, rel=1e-9)
    assert abs(h[2]) == pytest.approx(h2, rel=1e-9)
    # Only the mean torque and these two harmonics exist under assumptions (10).
    assert np.max(np.abs(h[3:])) < 1e-12
    kt = PAPER_MOTOR.kt_Nm_per_A
    assert h1 == pytest.approx(kt * math.hypot(I10, I20))


def test_eq18_as_printed_is_half_of_what_eq16_gives() -> None:
    """The paper's ¼·|I11 − I21| is a factor of two short of eq. (16)'s ½."""
    h = _ripple_phasors(PAPER_MOTOR, I10=0.0, I20=0.0, I11=0.9, I21=1.1, rho=0.2)
    printed = PAPER_MOTOR.kt_Nm_per_A * 0.25 * abs(0.9 - 1.1)
    assert abs(h[2]) == pytest.approx(2 * printed, rel=1e-9)


def test_first_harmonic_vanishes_at_zero_offset_whatever_the_gains() -> None:
    h = _ripple_phasors(PAPER_MOTOR, I10=0.0, I20=0.0, I11=0.8, I21=1.2, rho=0.3)
    assert abs(h[1]) < 1e-12
    assert abs(h[2]) > 1e-2


def test_paper_eq8_is_the_first_harmonic_special_case() -> None:
    theta = np.linspace(0.0, 0.5, 200)
    _, l2f = mutual_inductances(theta, PAPER_MOTOR)
    te = PAPER_MOTOR.rotor_teeth * theta
    np.testing.assert_allclose(l2f, PAPER_MOTOR.Lm0_H + PAPER_MOTOR.Lm1_H * np.sin(te), atol=1e-15)


def test_equal_harmonic_content_makes_phase_b_phase_a_shifted_by_a_quarter_tooth_pitch() -> None:
    harmonics = tuple(FluxHarmonic(j, 1e-5 * j, 0.3 * j) for j in (2, 3, 4, 5))
    motor = MotorParams(flux_a=harmonics, flux_b=harmonics)
    theta = np.linspace(0.0, 0.5, 300)
    l1f_shifted, _ = mutual_inductances(theta - math.pi / (2 * motor.rotor_teeth), motor)
    _, l2f = mutual_inductances(theta, motor)
    np.testing.assert_allclose(l2f, l1f_shifted, atol=1e-15)


def test_unequal_flux_harmonics_move_the_h1_null_away_from_zero_net_offset() -> None:
    motor = _every_effect_motor()
    null = _h1_null_offsets(MotorParams(flux_a=motor.flux_a, flux_b=motor.flux_b,
                                        Lm1_H=motor.Lm1_H), amplitude_A=1.0, rho=0.05)
    assert np.hypot(*null) > 1e-3  # more than 1 mA
    assert np.hypot(*null) < 0.05  # but a residual, not a different motor


def test_without_flux_harmonics_the_h1_null_is_at_zero_net_offset() -> None:
    null = _h1_null_offsets(PAPER_MOTOR, amplitude_A=1.0, rho=0.05)
    assert np.hypot(*null) < 1e-9


def test_equal_odd_flux_harmonics_leave_the_h1_null_at_zero() -> None:
    """Odd harmonics shared by both phases only make 2nd and 4th-order ripple."""
    odd = (FluxHarmonic(3, 8e-6, 0.4), FluxHarmonic(5, 4e-6, 1.1))
    null = _h1_null_offsets(MotorParams(flux_a=odd, flux_b=odd), amplitude_A=1.0, rho=0.05)
    assert np.hypot(*null) < 1e-9
