"""Effects in the other forms the world makes them: a bridge's dead time, unequal phases."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import Effect, LoadKind, Trims
from station.physics.motor import torque, torque_numerical
from station.physics.params import AmplifierParams, EffectForm, UnitParams, derive_unit
from station.physics.plant import (
    STAIRCASE_LAG_MICROSTEPS,
    DriveCommand,
    Plant,
    commanded_currents_A,
)
from station.sim.concealed import CLASSES, FORMS, TrialClass
from station.sim.population import DEAD_TIME_ERROR, UNEQUAL_PHASES, draw_unit

M = 256


def _unequal(unit: UnitParams, u: float) -> UnitParams:
    return replace(unit, motor=replace(unit.motor, L1_unequal=u))


def _dead(unit: UnitParams, dead_mA: float, knee_mA: float) -> UnitParams:
    amp = replace(unit.amplifier, distortion_a=(), distortion_b=(), dead_time_mA=dead_mA,
                  dead_time_knee_mA=knee_mA)
    return replace(unit, amplifier=amp)


def test_unequal_phases_keep_the_torque_the_derivative_of_the_inductance_matrix() -> None:
    motor = _unequal(derive_unit("SN4711", effects=list(Effect)), 0.6).motor
    rng = np.random.default_rng(2)
    theta = rng.uniform(-1.0, 1.0, 200)
    i_a, i_b = rng.uniform(-1.5, 1.5, 200), rng.uniform(-1.5, 1.5, 200)
    np.testing.assert_allclose(torque(theta, i_a, i_b, motor),
                               torque_numerical(theta, i_a, i_b, motor), rtol=1e-6, atol=1e-8)


def test_unequal_phases_add_a_second_harmonic_growing_with_the_current_squared() -> None:
    motor = derive_unit("SN4712", effects=[Effect.RELUCTANCE_TORQUE]).motor
    u = 0.5
    theta = np.linspace(0.0, 2 * math.pi / motor.rotor_teeth, 181)
    te = motor.rotor_teeth * theta
    for current in (0.3, 1.0):
        # Currents of any direction, |i| = current: the added torque sees only |i|².
        x = te + 0.4
        i_a, i_b = current * np.cos(x), current * np.sin(x)
        added = (torque(theta, i_a, i_b, replace(motor, L1_unequal=u))
                 - torque(theta, i_a, i_b, motor))
        expected = -motor.rotor_teeth * motor.L1_H * u * np.sin(2 * te) * current**2
        np.testing.assert_allclose(added, expected, rtol=1e-9, atol=1e-15)


def test_a_dead_time_is_an_error_of_fixed_size_against_the_currents_sign() -> None:
    amp = AmplifierParams(dead_time_mA=30.0, dead_time_knee_mA=10.0)
    x = np.linspace(0.0, 2 * math.pi, 721)
    i_a, i_b = commanded_currents_A(x, 800.0, Trims(), amp)
    ideal_a, ideal_b = commanded_currents_A(x, 800.0, Trims(), AmplifierParams())
    far = np.abs(ideal_a) > 0.1  # five knees from zero: the error has its full size
    np.testing.assert_allclose((i_a - ideal_a)[far], -0.030 * np.sign(ideal_a[far]), atol=1e-6)
    assert np.all(np.abs(i_b - ideal_b) <= 0.030 + 1e-12)
    # It turns smoothly through zero, as the PWM ripple's average does.
    assert np.all(np.abs(np.diff(i_a)) < 0.02)
    with pytest.raises(ValueError, match="dead-time"):
        AmplifierParams(dead_time_mA=-1.0)
    with pytest.raises(ValueError, match="dead-time"):
        AmplifierParams(dead_time_mA=10.0, dead_time_knee_mA=0.0)


@pytest.mark.parametrize("effects", [
    # Saturation and eccentricity reshape the torque: the plant's other branch.
    [e for e in Effect if e is not Effect.CURRENT_LOOP_LAG],
    [Effect.RELUCTANCE_TORQUE, Effect.CURRENT_DISTORTION],
])
def test_the_plant_makes_both_forms_as_the_motor_model_and_the_drive_say(
        effects: list[Effect]) -> None:
    unit = derive_unit("SN77", effects=effects)
    unit = _dead(_unequal(unit, -0.7), 25.0, 15.0)
    rng = np.random.default_rng(5)
    for _ in range(10):
        plant = Plant(unit, sync_period_s=1e-4, substeps=1)
        trims = Trims(*rng.uniform(-100, 100, 2), *rng.uniform(8000, 12000, 2))
        plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, rng.uniform(0, 5000),
                                               0.0, 0.0, M))
        theta = plant.rotor_angle_rad
        position = rng.uniform(0, 5000)
        plant.advance(DriveCommand(True, 800.0, trims, position, 0.0, 0.0, M))
        x = 2 * math.pi * (position - STAIRCASE_LAG_MICROSTEPS) / (4 * M)
        i_a, i_b = commanded_currents_A(x, 800.0, trims, unit.amplifier)
        assert plant.phase_currents_A == pytest.approx((float(i_a), float(i_b)), abs=1e-7)
        assert plant.motor_torque_Nm == pytest.approx(
            float(torque(theta, i_a, i_b, unit.motor)), abs=1e-7)


def test_a_drawn_form_replaces_the_default_and_leaves_every_other_draw_as_it_was() -> None:
    effects = frozenset({Effect.CURRENT_DISTORTION, Effect.RELUCTANCE_TORQUE})
    plain = draw_unit(31, load=LoadKind.BELT, effects=effects)
    formed = draw_unit(31, load=LoadKind.BELT, effects=effects,
                       forms=frozenset(EffectForm))
    rated_mA = plain.rated_current_mA
    assert plain.amplifier.dead_time_mA == 0.0 and plain.amplifier.distortion_a
    assert formed.amplifier.distortion_a == formed.amplifier.distortion_b == ()
    low, high = DEAD_TIME_ERROR
    assert low * rated_mA <= formed.amplifier.dead_time_mA <= high * rated_mA
    assert UNEQUAL_PHASES[0] <= abs(formed.motor.L1_unequal) <= UNEQUAL_PHASES[1]
    assert formed.motor.L1_H == plain.motor.L1_H
    assert replace(formed.motor, L1_unequal=0.0) == plain.motor
    assert replace(formed.amplifier, distortion_a=plain.amplifier.distortion_a,
                   distortion_b=plain.amplifier.distortion_b, dead_time_mA=0.0,
                   dead_time_knee_mA=plain.amplifier.dead_time_knee_mA) == plain.amplifier
    assert (formed.mechanics, formed.sensor) == (plain.mechanics, plain.sensor)


def test_a_form_of_an_id_the_unit_does_not_have_is_refused() -> None:
    with pytest.raises(ValueError, match="dead_time"):
        draw_unit(3, load=LoadKind.DISK, effects=frozenset({Effect.DETENT_TORQUE}),
                  forms=frozenset({EffectForm.DEAD_TIME}))
    with pytest.raises(ValueError, match="unequal_phases"):
        TrialClass(frozenset({Effect.DETENT_TORQUE}),
                   forms=frozenset({EffectForm.UNEQUAL_PHASES}))


def test_a_class_in_another_form_says_so_in_its_label() -> None:
    cls = TrialClass(frozenset({Effect.DETENT_TORQUE, Effect.RELUCTANCE_TORQUE}),
                     forms=frozenset({EffectForm.UNEQUAL_PHASES}))
    assert cls.label == "detent_torque+reluctance_torque:unequal_phases"
    assert not cls.control


def test_the_benchmark_draws_every_form_and_each_class_is_labelled_apart() -> None:
    assert set(FORMS) <= set(CLASSES)
    assert {f for cls in FORMS for f in cls.forms} == set(EffectForm)
    labels = [cls.label for cls in CLASSES]
    assert len(labels) == len(set(labels))
