"""The wide population: reproducible per seed, every constant over its range, every
effect switchable on its own, and every unit one the plant can run."""

from __future__ import annotations

import json
import math
from dataclasses import fields, replace
from typing import Any

import numpy as np
import pytest

from station.core import Effect, LoadKind, Trims
from station.limits import trims_within
from station.physics.optimum import optimal_trims
from station.physics.params import UnitParams, UnnamedEffect
from station.physics.plant import DriveCommand, Plant
from station.physics.truth import unit_truth
from station.recipes import load_recipe
from station.serials import parse_serial
from station.sim.population import (
    BELT_LOAD_SHARE,
    LINE_SHARES,
    Bearings,
    LineKind,
    belt_mode_motor_held_hz,
    draw_line_unit,
    draw_unit,
)

M = 256
T = 0.001
SEEDS = range(200)
EVERY = frozenset(Effect)
NONE: frozenset[Effect] = frozenset()


def _within(value: float, low: float, high: float) -> bool:
    return low * (1 - 1e-12) <= value <= high * (1 + 1e-12)


def test_the_same_seed_gives_the_same_unit_and_another_seed_another() -> None:
    for load in LoadKind:
        a = draw_unit(7, load=load, effects=EVERY, unnamed=frozenset(UnnamedEffect))
        assert a == draw_unit(7, load=load, effects=EVERY, unnamed=frozenset(UnnamedEffect))
        assert unit_truth(a) == unit_truth(draw_unit(7, load=load, effects=EVERY,
                                                     unnamed=frozenset(UnnamedEffect)))
        b = draw_unit(8, load=load, effects=EVERY)
        assert a.motor.kt_Nm_per_A != b.motor.kt_Nm_per_A
        assert a.amplifier.offset_a_mA != b.amplifier.offset_a_mA


def test_serials_are_valid_labels_apart_from_the_serial_derived_units() -> None:
    for seed in (0, 1, 99999, 123456):
        unit = draw_unit(seed, load=LoadKind.DISK, effects=NONE)
        parsed = parse_serial(unit.serial)
        assert (parsed.label, parsed.number) == (unit.serial, unit.serial_number)
        assert 900000 <= unit.serial_number < 1000000
    with pytest.raises(ValueError, match="seed"):
        draw_unit(-1, load=LoadKind.DISK, effects=NONE)


def test_motor_amplifier_and_sensor_span_their_wide_ranges() -> None:
    units = [draw_unit(seed, load=LoadKind.DISK, effects=NONE) for seed in SEEDS]
    for unit in units:
        motor, amp, sensor = unit.motor, unit.amplifier, unit.sensor
        assert motor.rotor_teeth == 50 and motor.field_current_A == 10.0
        assert _within(motor.kt_Nm_per_A, 0.2, 0.6)
        assert _within(motor.rotor_inertia_kgm2, 3e-6, 1.5e-5)
        assert unit.rated_current_mA == 1000 and unit.microsteps == 256
        assert abs(amp.offset_a_mA) <= 200 and abs(amp.offset_b_mA) <= 200
        assert abs(amp.gain_error_a) <= 0.1 and abs(amp.gain_error_b) <= 0.1
        assert _within(sensor.noise_density_ug, 100, 400)
        assert _within(sensor.bandwidth_hz, 400, 1000)
        assert _within(sensor.damping_ratio, 0.6, 0.8)
        assert sensor.range_g == 2
        disk = unit.mechanics.disk
        assert disk is not None and _within(disk.inertia_kgm2, 5e-6, 1e-4)
        assert _within(sensor.radius_m, 0.02, 0.12)
        # A healthy unit's bearings (CLI.md): Coulomb friction up to 10 % of the holding
        # torque, each direction its own, and viscous drag.
        bearing = unit.mechanics.rotor_bearing
        holding = unit.motor.holding_torque_Nm(1.0)
        for level in (bearing.coulomb_pos_Nm, bearing.coulomb_neg_Nm):
            assert _within(level / holding, 0.01, 0.10)
        assert _within(bearing.viscous_Nms, 0.001, 0.004)
    # Wide means wide: the draws reach towards both ends.
    kts = [u.motor.kt_Nm_per_A for u in units]
    assert min(kts) < 0.25 and max(kts) > 0.55
    inertias = [u.mechanics.disk.inertia_kgm2 for u in units]  # type: ignore[union-attr]
    assert min(inertias) < 1e-5 and max(inertias) > 5e-5
    assert draw_unit(3, load=LoadKind.DISK, effects=NONE,
                     noise_density_ug=0.0).sensor.noise_density_ug == 0.0
    forward = [u.mechanics.rotor_bearing.coulomb_pos_Nm / u.motor.holding_torque_Nm(1.0)
               for u in units]
    reverse = [u.mechanics.rotor_bearing.coulomb_neg_Nm / u.motor.holding_torque_Nm(1.0)
               for u in units]
    assert min(forward) < 0.03 and max(forward) > 0.08
    assert any(abs(f - r) > 0.03 for f, r in zip(forward, reverse, strict=True))


def test_units_at_the_healthy_limit_have_bearings_just_under_it_and_nothing_else_changes(
) -> None:
    for seed in SEEDS[:8]:
        plain = draw_unit(seed, load=LoadKind.DISK, effects=NONE)
        limit = draw_unit(seed, load=LoadKind.DISK, effects=NONE, bearings=Bearings.AT_LIMIT)
        holding = limit.motor.holding_torque_Nm(1.0)
        bearing = limit.mechanics.rotor_bearing
        for level in (bearing.coulomb_pos_Nm, bearing.coulomb_neg_Nm):
            assert _within(level / holding, 0.09, 0.10)
        assert limit.motor == plain.motor and limit.sensor == plain.sensor
        assert bearing.viscous_Nms == plain.mechanics.rotor_bearing.viscous_Nms


def test_belts_span_gear_ratio_mode_inertia_and_damping() -> None:
    modes = []
    for seed in SEEDS:
        unit = draw_unit(seed, load=LoadKind.BELT, effects=NONE)
        belt = unit.mechanics.belt
        assert belt is not None
        assert _within(unit.gear_ratio, 0.1, 0.5)
        f_held = belt_mode_motor_held_hz(belt)
        # The same, from scratch: the load swinging on the belt, both at the load shaft.
        assert f_held == pytest.approx(
            math.sqrt(belt.stiffness_Nm_per_rad / belt.load_inertia_kgm2) / (2 * math.pi))
        assert _within(f_held, 30.0, 500.0)
        modes.append(f_held)
        zeta = belt.damping_Nms_per_rad / (
            2 * math.sqrt(belt.stiffness_Nm_per_rad * belt.load_inertia_kgm2))
        assert _within(zeta, 0.02, 0.2)
        assert _within(belt.motor_pulley_inertia_kgm2, 3e-6, 2e-5)
        seen = belt.load_inertia_kgm2 * belt.reduction**2 / unit.motor.rotor_inertia_kgm2
        assert _within(seen, 0.3, 30.0)
        assert _within(unit.sensor.radius_m, 0.05, 0.15)
        # The bearings' Coulomb friction shared between motor and load, up to 10 % of the
        # holding torque at the motor shaft in all (a load torque is ·n there).
        bearing = unit.mechanics.load_bearing
        rotor = unit.mechanics.rotor_bearing
        assert bearing is not None and bearing.viscous_Nms > 0.0
        holding = unit.motor.holding_torque_Nm(1.0)
        for at_rotor, at_load in ((rotor.coulomb_pos_Nm, bearing.coulomb_pos_Nm),
                                  (rotor.coulomb_neg_Nm, bearing.coulomb_neg_Nm)):
            assert _within((at_rotor + at_load * unit.gear_ratio) / holding, 0.01, 0.10)
            share = at_load * unit.gear_ratio / (at_rotor + at_load * unit.gear_ratio)
            assert _within(share, *BELT_LOAD_SHARE)
    # Log-uniform: as many modes in each half of the log range.
    below = sum(f < math.sqrt(30.0 * 500.0) for f in modes)
    assert 0.35 * len(modes) < below < 0.65 * len(modes)


def _peak_detent(unit: UnitParams, order: int) -> float:
    motor = unit.motor
    (d,) = [d for d in motor.detent if d.order == order]
    return 0.5 * d.order * motor.rotor_teeth * d.amplitude_H * motor.field_current_A**2


def test_every_effect_spans_its_range() -> None:
    symmetric = 0
    for seed in SEEDS:
        load = LoadKind.BELT if seed % 2 else LoadKind.DISK
        unit = draw_unit(seed, load=load, effects=EVERY)
        motor, amp, mech, sensor = unit.motor, unit.amplifier, unit.mechanics, unit.sensor
        holding = motor.holding_torque_Nm(1.0)
        for h in (*motor.flux_a, *motor.flux_b):
            assert _within(h.amplitude_H / motor.Lm1_H, 0.002, 0.01)
        if motor.flux_a == motor.flux_b:
            symmetric += 1
            assert [h.order for h in motor.flux_a] == [3, 5]
        else:
            assert [h.order for h in motor.flux_a] == [2, 3, 4, 5]
        peak4 = abs(_peak_detent(unit, 4))
        assert _within(peak4 / holding, 0.01, 0.04)
        assert _within(abs(_peak_detent(unit, 8)) / peak4, 0.1, 0.3)
        assert _within(motor.rotor_teeth * motor.L1_H / motor.kt_Nm_per_A, 0.02, 0.06)
        assert mech.coupling is not None
        assert _within(mech.coupling.resonance_hz, 60, 400)
        assert _within(mech.coupling.damping_ratio, 0.02, 0.1)
        for c in (*amp.distortion_a, *amp.distortion_b):
            assert c.order in (2, 3, 5) and _within(c.relative, 0.003, 0.015)
        assert amp.bandwidth_a_hz is not None and amp.bandwidth_b_hz is not None
        for bw in (amp.bandwidth_a_hz, amp.bandwidth_b_hz):
            assert _within(1 / (2 * math.pi * bw), 0.1e-3, 1e-3)
        assert abs(amp.bandwidth_a_hz / amp.bandwidth_b_hz - 1) <= 0.05
        friction = mech.load_friction
        assert friction is not None
        holding_load = holding / unit.gear_ratio
        # Beyond a healthy unit's, from 1.5 times CLI.md's limit.
        assert _within(friction.coulomb_pos_Nm / holding_load, 0.15, 0.3)
        assert _within(friction.coulomb_neg_Nm / friction.coulomb_pos_Nm, 0.7, 1.3)
        load_speed = 2 * math.pi * 20.0 / motor.rotor_teeth * unit.gear_ratio
        assert _within(friction.viscous_Nms * load_speed / holding_load, 0.02, 0.1)
        assert _within(abs(sensor.clock_drift_ppm), 100, 500)
        drop = 1 - float(motor.saturation_factor(1.0))
        assert _within(drop, 0.05, 0.2)
        assert motor.eccentricity is not None
        assert _within(motor.eccentricity.relative, 0.03, 0.1)
        assert motor.eccentricity.unbalance_Nm <= 0.02 * holding
    assert 0.3 * len(SEEDS) < symmetric < 0.7 * len(SEEDS)


def test_unnamed_effects_span_their_ranges_and_stay_out_of_the_effects() -> None:
    for seed in SEEDS:
        unit = draw_unit(seed, load=LoadKind.DISK, effects=NONE,
                         unnamed=frozenset(UnnamedEffect))
        s = unit.sensor
        assert _within(abs(s.nonlinearity_c2) + abs(s.nonlinearity_c3), 0.005, 0.03)
        assert _within(abs(math.degrees(s.tilt_rad)), 5.0, 20.0)
        assert unit.effects == NONE
        assert unit.unnamed_effects == frozenset(UnnamedEffect)
        truth = json.loads(json.dumps(unit_truth(unit)))
        assert truth["effects"] == []
        assert {e["id"] for e in truth["out_of_vocabulary"]} == {u.value for u in UnnamedEffect}


def _off_values(unit: UnitParams, switched: Effect | UnnamedEffect) -> UnitParams:
    """``unit`` with the constants of one effect put back to 'not there'."""
    m, a, mech, s = unit.motor, unit.amplifier, unit.mechanics, unit.sensor
    changes: dict[str, Any] = {}
    match switched:
        case Effect.FLUX_HARMONICS:
            changes["motor"] = replace(m, flux_a=(), flux_b=())
        case Effect.DETENT_TORQUE:
            changes["motor"] = replace(m, detent=())
        case Effect.RELUCTANCE_TORQUE:
            changes["motor"] = replace(m, L1_H=0.0)
        case Effect.MAGNETIC_SATURATION:
            changes["motor"] = replace(m, saturation_current_A=None)
        case Effect.ROTOR_ECCENTRICITY:
            changes["motor"] = replace(m, eccentricity=None)
        case Effect.LOAD_RESONANCE:
            changes["mechanics"] = replace(mech, coupling=None)
        case Effect.FRICTION:
            changes["mechanics"] = replace(mech, load_friction=None)
        case Effect.CURRENT_DISTORTION:
            changes["amplifier"] = replace(a, distortion_a=(), distortion_b=())
        case Effect.CURRENT_LOOP_LAG:
            changes["amplifier"] = replace(a, bandwidth_a_hz=None, bandwidth_b_hz=None)
        case Effect.SENSOR_CLOCK_DRIFT:
            changes["sensor"] = replace(s, clock_drift_ppm=0.0, sample_phase=0.0)
        case UnnamedEffect.SENSOR_NONLINEARITY:
            changes["sensor"] = replace(s, nonlinearity_c2=0.0, nonlinearity_c3=0.0)
        case UnnamedEffect.SENSOR_TILT:
            changes["sensor"] = replace(s, tilt_rad=0.0)
    if isinstance(switched, Effect):
        changes["effects"] = unit.effects - {switched}
    return replace(unit, **changes)


def _readings(unit: UnitParams, syncs: int = 400) -> np.ndarray:
    plant = Plant(replace(unit, sensor=replace(unit.sensor, noise_density_ug=0.0)))
    velocity = 20.0 * 4 * M
    trims = Trims(20.0, -10.0, 10100.0, 9900.0)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    out = []
    for k in range(syncs):
        plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity, 0.0, M))
        out.append(plant.sensor_reading_mps2)
    return np.array(out)


SWITCHES: list[Effect | UnnamedEffect] = [*Effect, *UnnamedEffect]


@pytest.mark.parametrize("switched", SWITCHES, ids=[s.value for s in SWITCHES])
@pytest.mark.parametrize("load", list(LoadKind))
def test_each_effect_switches_on_alone_and_changes_the_output(
        switched: Effect | UnnamedEffect, load: LoadKind) -> None:
    seed = 11
    plain = draw_unit(seed, load=load, effects=NONE)
    if isinstance(switched, Effect):
        on = draw_unit(seed, load=load, effects=frozenset({switched}))
    else:
        on = draw_unit(seed, load=load, effects=NONE, unnamed=frozenset({switched}))
    assert on != plain
    # Everything else is exactly the unit without it: its own stream, nothing shared.
    assert _off_values(on, switched) == plain
    before = _readings(plain)
    np.testing.assert_array_equal(before, _readings(_off_values(on, switched)))
    assert not np.array_equal(before, _readings(on))


def test_switching_effects_does_not_move_any_other_constant() -> None:
    every = draw_unit(5, load=LoadKind.BELT, effects=EVERY, unnamed=frozenset(UnnamedEffect))
    stripped = every
    for switched in SWITCHES:
        stripped = _off_values(stripped, switched)
    assert stripped == draw_unit(5, load=LoadKind.BELT, effects=NONE)


@pytest.mark.parametrize("load", list(LoadKind))
def test_the_plant_runs_every_drawn_unit_stably(load: LoadKind) -> None:
    """Stiff belts on light rotors ring at kilohertz: the plant takes the substeps they need."""
    for seed in range(0, 40, 3):
        unit = draw_unit(seed, load=load, effects=EVERY, unnamed=frozenset(UnnamedEffect))
        for hz in (6.0, 40.0):
            plant = Plant(unit, seed=seed)
            velocity = hz * 4 * M
            trims = Trims(-unit.amplifier.offset_a_mA, -unit.amplifier.offset_b_mA)
            plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
            for k in range(600):
                plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity,
                                           0.0, M))
            assert all(math.isfinite(v) for v in plant.sensor_reading_mps2)
            # It follows the field: within a quarter electrical period, no step lost.
            field = 2 * math.pi * hz / unit.rotor_teeth * 600 * T
            assert plant.rotor_angle_rad == pytest.approx(field, abs=math.pi / 2 / unit.rotor_teeth)


def test_the_truth_is_json_with_every_constant_and_effect() -> None:
    unit = draw_unit(3, load=LoadKind.BELT, effects=EVERY, unnamed=frozenset(UnnamedEffect))
    truth = json.loads(json.dumps(unit_truth(unit)))
    assert truth["serial"] == unit.serial and truth["load"] == "belt"
    assert truth["gear_ratio"] == unit.gear_ratio
    assert [e["id"] for e in truth["effects"]] == sorted(e.value for e in Effect)
    assert len(truth["out_of_vocabulary"]) == len(UnnamedEffect)
    assert {f.name for f in fields(unit.sensor)} <= set(truth["sensor"])


# --------------------------------------------------------------------------- a line's units
LINE = [draw_line_unit(seed) for seed in range(400)]


def test_a_line_unit_is_the_same_for_the_same_seed_and_is_that_seeds_population_unit() -> None:
    for line in LINE[:20]:
        assert draw_line_unit(line.seed) == line
        drawn = draw_unit(line.seed, load=line.unit.load, effects=line.unit.effects,
                          bearings=Bearings.VISCOUS_ONLY)
        # The line changes the amplifier of a rough or untrimmable unit, nothing else.
        assert replace(line.unit, amplifier=drawn.amplifier) == drawn
        if line.kind is LineKind.ORDINARY:
            assert line.unit == drawn


def test_a_line_sends_every_kind_both_loads_and_every_effect_alone_and_combined() -> None:
    for kind, share in LINE_SHARES.items():
        seen = sum(line.kind is kind for line in LINE) / len(LINE)
        assert abs(seen - share) < 0.06, (kind, seen)
    assert {line.unit.load for line in LINE} == set(LoadKind)
    clock = Effect.SENSOR_CLOCK_DRIFT
    assert 0.4 < sum(clock in line.unit.effects for line in LINE) / len(LINE) < 0.6
    ordinary = [line.unit.effects - {clock} for line in LINE if line.kind is LineKind.ORDINARY]
    for effect in set(Effect) - {clock}:
        assert frozenset({effect}) in ordinary, effect
        assert any(effect in e and len(e) == 2 for e in ordinary), effect
    assert frozenset() in ordinary


def test_rough_units_carry_large_errors_and_strong_ripple_effects() -> None:
    rough = [line.unit for line in LINE if line.kind is LineKind.ROUGH]
    assert rough
    for unit in rough:
        assert {Effect.DETENT_TORQUE, Effect.FLUX_HARMONICS} <= unit.effects
        amp = unit.amplifier
        assert min(abs(amp.offset_a_mA), abs(amp.offset_b_mA)) >= 150.0
        assert amp.gain_error_a == -amp.gain_error_b and abs(amp.gain_error_a) >= 0.06


def test_a_unit_drawn_out_of_bounds_has_its_optimum_beyond_the_recipes_bounds() -> None:
    limits = {name: load_recipe(name).limits for name in ("default", "paper")}
    beyond = [line.unit for line in LINE if line.kind is LineKind.OUT_OF_BOUNDS][:6]
    ordinary = [line.unit for line in LINE if line.kind is LineKind.ORDINARY][:6]
    assert len(beyond) == 6
    for unit in beyond:
        truth = optimal_trims(unit)
        assert not any(trims_within(lim, truth) for lim in limits.values()), truth
    for unit in ordinary:
        truth = optimal_trims(unit)
        assert all(trims_within(lim, truth) for lim in limits.values()), truth
