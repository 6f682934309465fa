"""Magnetic saturation: the magnet torque per ampere falls as the current vector grows."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import Effect, Trims
from station.physics.motor import (
    MotorParams,
    magnetic_stiffness,
    saturation_current_for_drop,
    torque,
    torque_components,
)
from station.physics.params import AmplifierParams, derive_unit
from station.physics.plant import STAIRCASE_LAG_MICROSTEPS, DriveCommand, Plant
from station.physics.truth import unit_truth

M = 256
SERIALS = [f"SN{n}" for n in range(2000, 2100)]


def _peak_torque_per_ampere(motor: MotorParams, current_A: float) -> float:
    """Torque per ampere with the field a quarter period ahead of the rotor (sin ρ = 1)."""
    theta = 0.0137
    x = motor.rotor_teeth * theta + math.pi / 2
    return float(torque(theta, current_A * math.cos(x), current_A * math.sin(x), motor)) / current_A


def test_the_drawn_drop_of_the_torque_constant_at_rated_current_is_5_to_20_percent() -> None:
    for serial in SERIALS:
        unit = derive_unit(serial, effects=[Effect.MAGNETIC_SATURATION])
        drop = 1.0 - float(unit.motor.saturation_factor(unit.rated_current_mA / 1000.0))
        assert 0.05 <= drop <= 0.20


def test_torque_per_ampere_at_rated_current_is_lower_than_at_low_current_by_the_drop() -> None:
    unit = derive_unit("SN2001", effects=[Effect.MAGNETIC_SATURATION])
    truth = {e["id"]: e["parameters"] for e in unit_truth(unit)["effects"]}
    drop = truth["magnetic_saturation"]["kt_drop_at_rated"]
    low = _peak_torque_per_ampere(unit.motor, 0.001)
    rated = _peak_torque_per_ampere(unit.motor, 1.0)
    assert low == pytest.approx(unit.motor.kt_Nm_per_A, rel=1e-6)
    assert rated / low == pytest.approx(1.0 - drop, rel=1e-6)
    assert rated == pytest.approx((1.0 - drop) * unit.motor.kt_Nm_per_A, rel=1e-9)
    plain = derive_unit("SN2001", effects=())
    assert _peak_torque_per_ampere(plain.motor, 1.0) == pytest.approx(plain.motor.kt_Nm_per_A)


def test_the_plant_applies_the_same_drop_to_its_torque() -> None:
    """One step per SYNC: the torque reported is the motor's at the angle it started from."""
    plain = derive_unit("SN2002", effects=())
    plain = replace(plain, amplifier=AmplifierParams())
    saturated = replace(plain, motor=derive_unit("SN2002",
                                                 effects=[Effect.MAGNETIC_SATURATION]).motor)
    position = M + STAIRCASE_LAG_MICROSTEPS  # the field a quarter period ahead of the rotor
    torques = []
    for unit in (plain, saturated):
        plant = Plant(unit, sync_period_s=1e-4, substeps=1)
        plant.advance(DriveCommand(True, 1000.0, Trims(), position, 0.0, 0.0, M))
        torques.append(plant.motor_torque_Nm)
    g = float(saturated.motor.saturation_factor(1.0))
    assert torques[0] == pytest.approx(plain.motor.kt_Nm_per_A, rel=1e-6)
    assert torques[1] / torques[0] == pytest.approx(g, rel=1e-9)


def test_saturation_scales_the_whole_magnet_torque_by_the_current_vectors_magnitude_only() -> None:
    """Fundamental and flux harmonics alike, whatever the current's direction; not
    reluctance or detent, which do not ride on the stator current through L1f/L2f."""
    effects = [Effect.FLUX_HARMONICS, Effect.DETENT_TORQUE, Effect.RELUCTANCE_TORQUE]
    plain = derive_unit("SN2003", effects=effects).motor
    saturated = derive_unit("SN2003", effects=[*effects, Effect.MAGNETIC_SATURATION]).motor
    rng = np.random.default_rng(1)
    theta = rng.uniform(0, 2 * math.pi, 200)
    i_a, i_b = rng.uniform(-1.5, 1.5, (2, 200))
    pm0, vr0, cg0 = torque_components(theta, i_a, i_b, plain)
    pm1, vr1, cg1 = torque_components(theta, i_a, i_b, saturated)
    g = saturated.saturation_factor(np.hypot(i_a, i_b))
    np.testing.assert_allclose(pm1, g * pm0, rtol=1e-12, atol=1e-15)
    np.testing.assert_array_equal(vr1, vr0)
    np.testing.assert_array_equal(cg1, cg0)
    np.testing.assert_allclose(torque(theta, i_a, i_b, saturated), pm1 + vr1 + cg1, atol=1e-15)


def test_the_saturation_law_is_one_at_zero_decreasing_and_keeps_the_torque_rising() -> None:
    motor = MotorParams(saturation_current_A=saturation_current_for_drop(1.0, 0.2))
    currents = np.linspace(0.0, 5.0, 501)
    g = motor.saturation_factor(currents)
    assert g[0] == 1.0
    assert np.all(np.diff(g) < 0)
    assert np.all(np.diff(g * currents) > 0)
    assert float(motor.saturation_factor(1.0)) == pytest.approx(0.8)
    assert np.all(MotorParams().saturation_factor(currents) == 1.0)


def test_saturation_softens_the_magnetic_spring_by_the_same_factor() -> None:
    unit = derive_unit("SN2004", effects=[Effect.MAGNETIC_SATURATION])
    plain = derive_unit("SN2004", effects=()).motor
    g = float(unit.motor.saturation_factor(0.8))
    assert magnetic_stiffness(unit.motor, 800.0, 0.3) == pytest.approx(
        g * magnetic_stiffness(plain, 800.0, 0.3), rel=1e-12)


def test_the_truth_gives_the_law_and_its_constants() -> None:
    unit = derive_unit("SN2005", effects=[Effect.MAGNETIC_SATURATION])
    truth = json.loads(json.dumps(unit_truth(unit)))
    (entry,) = truth["effects"]
    assert entry["id"] == "magnetic_saturation"
    params = entry["parameters"]
    assert params["saturation_current_A"] == unit.motor.saturation_current_A
    assert 0.05 <= params["kt_drop_at_rated"] <= 0.20
    assert params["holding_torque_at_rated_Nm"] == pytest.approx(
        truth["holding_torque_Nm"] * (1 - params["kt_drop_at_rated"]))
    assert "sqrt" in params["law"]
