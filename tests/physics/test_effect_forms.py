"""Effects in the other forms the world makes them: a bridge's dead time, unequal phases,
a second mode beyond a declared belt."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import Effect, LoadKind, Trims
from station.physics.motor import torque, torque_numerical
from station.physics.params import (
    AmplifierParams,
    EffectForm,
    PhaseCircuit,
    UnitParams,
    derive_unit,
)
from station.physics.plant import (
    STAIRCASE_LAG_MICROSTEPS,
    DriveCommand,
    Plant,
    build_chain,
    commanded_currents_A,
    modal_analysis,
)
from station.sim.concealed import CLASSES, FORMS, TrialClass
from station.sim.population import (
    DEAD_TIME_ERROR,
    SECOND_MODE_ABOVE_BELT,
    SECOND_MODE_SHARE,
    UNEQUAL_PHASES,
    draw_unit,
)

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
                       forms=frozenset({EffectForm.DEAD_TIME, EffectForm.UNEQUAL_PHASES}))
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


def test_a_second_belt_mode_splits_the_load_beyond_the_belt_and_rings_where_drawn() -> None:
    """The form puts a compliance beyond the belt, not at the rotor: the chain is rotor and
    pulley, the belt, the load's near part, its own compliance, the part the sensor is on;
    no coupling at the rotor; and with the rest of the load held, that part rings at the
    drawn frequency, above the belt's own mode."""
    effects = frozenset({Effect.LOAD_RESONANCE})
    plain = draw_unit(31, load=LoadKind.BELT, effects=effects)
    formed = draw_unit(31, load=LoadKind.BELT, effects=effects,
                       forms=frozenset({EffectForm.SECOND_BELT_MODE}))
    belt, second = formed.mechanics.belt, None
    assert belt is not None and plain.mechanics.belt is not None
    second = belt.second_mode
    assert second is not None and formed.mechanics.coupling is None
    assert plain.mechanics.coupling is not None and plain.mechanics.belt.second_mode is None
    assert SECOND_MODE_SHARE[0] <= second.share <= SECOND_MODE_SHARE[1]
    held = math.sqrt(belt.stiffness_Nm_per_rad / belt.load_inertia_kgm2) / (2 * math.pi)
    assert SECOND_MODE_ABOVE_BELT[0] <= second.resonance_hz / held <= SECOND_MODE_ABOVE_BELT[1]
    chain = build_chain(formed)
    assert chain.ratios == (belt.reduction, 1.0)
    assert sum(chain.inertias[1:]) == pytest.approx(belt.load_inertia_kgm2)
    beyond = chain.inertias[2]
    assert math.sqrt(second.stiffness_Nm_per_rad / beyond) / (2 * math.pi) == pytest.approx(
        second.resonance_hz)
    # One more mode than the belt alone has, and the highest above the second mode's own.
    plain_modes = modal_analysis(replace(formed, mechanics=replace(
        formed.mechanics, belt=replace(belt, second_mode=None))), 1000.0)
    modes = modal_analysis(formed, 1000.0)
    assert len(modes) == len(plain_modes) + 1
    assert modes[-1].frequency_hz > second.resonance_hz
    with pytest.raises(ValueError, match="belt"):
        draw_unit(31, load=LoadKind.DISK, effects=effects,
                  forms=frozenset({EffectForm.SECOND_BELT_MODE}))


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


def _pi_currents(bandwidth_hz: float, circuit: PhaseCircuit, kt: float, speed: float,
                 electrical_hz: float, periods: int, h: float) -> tuple[np.ndarray, np.ndarray]:
    """Phase A's current and its command through the kernel's PI loop, the rotor turning
    at ``speed`` (rad/s, an inertia so large that it never changes) and the drive's angle
    at ``electrical_hz``: one SYNC period of ``periods`` electrical periods, sampled every
    step."""
    from station.physics import kernel as k_  # noqa: PLC0415 (the kernel's layout)

    c = np.zeros(k_.N_CONSTANTS)
    c[k_.H], c[k_.NR], c[k_.KT] = h, 50.0, kt
    wb = 2.0 * math.pi * bandwidth_hz
    c[k_.LA0:k_.LA2 + 1] = c[k_.LB0:k_.LB2 + 1] = (
        wb, circuit.resistance_ohm / circuit.inductance_H, 1.0 / circuit.inductance_H)
    c[k_.IW0] = c[k_.IWL] = 1.0
    c[k_.J0] = c[k_.J1] = c[k_.JL] = 1e12  # the rotor's speed stays as it was set
    sw = np.zeros(k_.N_SWITCHES, dtype=np.int64)
    sw[k_.NDOF], sw[k_.LAGGED], sw[k_.PI_LOOP] = 1, 1, 1
    cmd = np.zeros(k_.N_COMMAND)
    cmd[k_.ENABLED], cmd[k_.KX], cmd[k_.FA], cmd[k_.FB] = 1.0, 1.0, 1.0, 1.0
    cmd[k_.PV] = 2.0 * math.pi * electrical_hz
    state = np.zeros(k_.N_STATE)
    state[k_.OM0] = speed
    empty = np.zeros((0, k_.TABLE_SIZE + 1))
    n = round(periods / (electrical_hz * h))
    out_i, out_u = np.zeros(n), np.zeros(n)
    for j in range(n):
        # One step at a time, so that each step's current can be read.
        cmd[k_.P0] = cmd[k_.PV] * j * h
        steps = np.array([[0.0, 0.0, 0.0]])
        k_.integrate(c, sw, cmd, state, empty, empty, np.zeros(0), steps, np.zeros(1))
        out_i[j], out_u[j] = state[k_.I_A], math.cos(cmd[k_.P0])
    return out_i, out_u


def test_a_pi_loop_follows_its_command_as_a_first_order_lag_and_rejects_back_emf_as_tuned(
) -> None:
    """Command to current is the first-order lag of the loop's bandwidth whatever R and L
    (the tuning puts the controller's zero on the phase's pole); the back-EMF, speed times
    ∂τ/∂i = −kt·sin θe, leaves a current of −e·s/(L(s + ωb)(s + R/L)) on top."""
    circuit = PhaseCircuit(2.0, 4e-3)
    bandwidth, f_e, h = 120.0, 30.0, 2e-6
    w = 2.0 * math.pi * f_e
    wb, r = 2.0 * math.pi * bandwidth, circuit.resistance_ohm / circuit.inductance_H
    s = 1j * w
    lag = wb / (s + wb)
    for speed, kt in ((0.0, 0.4), (w / 50.0, 0.4)):
        current, _ = _pi_currents(bandwidth, circuit, kt, speed, f_e, 12, h)
        t = np.arange(current.size) * h
        last = t >= t[-1] - 2.0 / f_e  # two periods, long after the loop settled
        phasor = 2.0 * np.mean(current[last] * np.exp(-1j * w * t[last]))
        # The rotor's angle turns with the drive's here (θe = ω·t): e_a = −kt·speed·sin θe.
        emf = -kt * speed * (-1j)  # sin θe is Re(−j·e^{jθe})
        expected = lag * 1.0 - emf * s / (circuit.inductance_H * (s + wb) * (s + r))
        assert abs(phasor - expected) < 0.01 * abs(expected), (speed, phasor, expected)
