"""Rotor eccentricity: airgap torque and load once per mechanical revolution."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import Effect, LoadKind, Trims
from station.dsp.demod import harmonic_phasors
from station.physics.motor import Eccentricity, magnetic_stiffness, torque, torque_components
from station.physics.params import AmplifierParams, DiskParams, UnitParams, derive_unit
from station.physics.plant import STAIRCASE_LAG_MICROSTEPS, DriveCommand, Plant
from station.physics.truth import unit_truth
from station.sim.population import draw_line_unit

M = 256
T = 0.001
SERIALS = [f"SN{n}" for n in range(3000, 3100)]


def test_drawn_eccentricity_is_3_to_10_percent_with_a_small_unbalance() -> None:
    phases = []
    for serial in SERIALS:
        unit = derive_unit(serial, effects=[Effect.ROTOR_ECCENTRICITY])
        ecc = unit.motor.eccentricity
        assert ecc is not None
        assert 0.03 <= ecc.relative <= 0.10
        assert 0 < ecc.unbalance_Nm <= 0.02 * unit.motor.holding_torque_Nm(1.0)
        phases.append(ecc.phase_rad)
    assert min(phases) < 1.0 and max(phases) > 2 * math.pi - 1.0


def test_airgap_torque_follows_the_mechanical_angle_not_the_electrical_one() -> None:
    """Half a revolution apart (25 electrical periods: the same electrical angle), the
    magnet, reluctance and detent torques differ by (1 + ε·cos)/(1 − ε·cos)."""
    effects = [Effect.DETENT_TORQUE, Effect.RELUCTANCE_TORQUE, Effect.FLUX_HARMONICS]
    plain = derive_unit("SN3001", effects=effects).motor
    eccentric = derive_unit("SN3001", effects=[*effects, Effect.ROTOR_ECCENTRICITY]).motor
    ecc = eccentric.eccentricity
    assert ecc is not None
    theta = np.linspace(0.0, 0.3, 7) - ecc.phase_rad
    i_a, i_b = 0.3, -0.8
    for rotor in (theta, theta + math.pi):
        expected = 1 + ecc.relative * np.cos(rotor + ecc.phase_rad)
        for part0, part1 in zip(torque_components(rotor, i_a, i_b, plain),
                                torque_components(rotor, i_a, i_b, eccentric), strict=True):
            np.testing.assert_allclose(part1, expected * part0, rtol=1e-12, atol=1e-15)
    near = torque(theta, i_a, i_b, eccentric) / torque(theta, i_a, i_b, plain)
    far = torque(theta + math.pi, i_a, i_b, eccentric) / torque(theta + math.pi, i_a, i_b, plain)
    np.testing.assert_allclose(near / far, (1 + ecc.relative) / (1 - ecc.relative), rtol=0.01)


def _order1_over_a_revolution(unit: UnitParams, electrical_hz: float,
                              periods_per_window: int) -> tuple[np.ndarray, np.ndarray]:
    """|H1| of the tangential reading in consecutive windows over one revolution, and
    the rotor's mean mechanical angle in each."""
    plant = Plant(unit)
    velocity = electrical_hz * 4 * M
    trims = Trims(100.0, 0.0)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    settle = round(2.0 / T)
    revolution = round(unit.rotor_teeth / electrical_hz / T)
    acc, rotor = [], []
    for k in range(settle + revolution):
        plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity, 0.0, M))
        if k >= settle:
            acc.append(plant.sensor_reading_mps2[0])
            rotor.append(plant.rotor_angle_rad)
    x = 2 * math.pi * velocity * np.arange(settle + 1, settle + revolution + 1) * T / (4 * M)
    n = round(periods_per_window / electrical_hz / T)
    amplitudes, angles = [], []
    for start in range(0, revolution - n + 1, n):
        window = slice(start, start + n)
        amplitudes.append(abs(harmonic_phasors(np.array(acc[window]), x[window], [1])[0]))
        angles.append(float(np.mean(rotor[window])))
    return np.array(amplitudes), np.array(angles)


def _once_per_revolution(amplitudes: np.ndarray, angles: np.ndarray) -> tuple[float, float]:
    """Relative depth ε' and phase φ' of amplitudes ≈ a0·(1 + ε'·cos(θ + φ'))."""
    design = np.column_stack([np.ones_like(angles), np.cos(angles), np.sin(angles)])
    a0, a1, b1 = np.linalg.lstsq(design, amplitudes, rcond=None)[0]
    return float(math.hypot(a1, b1) / a0), float(math.atan2(-b1, a1))


def _heavy_disk(unit: UnitParams, inertia: float) -> UnitParams:
    return replace(unit, amplifier=AmplifierParams(),
                   sensor=replace(unit.sensor, noise_density_ug=0.0),
                   mechanics=replace(unit.mechanics, disk=DiskParams(inertia)))


def test_an_inertia_dominated_ripple_swings_by_twice_the_eccentricity_over_a_revolution() -> None:
    """Far above the rotor's own mode, α ≈ τ/J: the order-1 ripple from an offset
    follows the airgap torque, (1 ± ε) at opposite sides of the revolution."""
    disk = 0.1
    hz, periods = 20.0, 5
    unit = _heavy_disk(derive_unit("SN123", effects=[Effect.ROTOR_ECCENTRICITY]), disk)
    ecc = unit.motor.eccentricity
    assert ecc is not None
    amplitudes, angles = _order1_over_a_revolution(unit, hz, periods)
    depth, phase = _once_per_revolution(amplitudes, angles)
    # What is left of the spring (r = Jω²/K) and of averaging over a window of the revolution.
    r = (disk + unit.motor.rotor_inertia_kgm2) * (2 * math.pi * hz) ** 2 / magnetic_stiffness(
        unit.motor, 1000.0)
    half_window = math.pi * periods / unit.rotor_teeth
    expected = ecc.relative * (1 + 1 / (r - 1)) * math.sin(half_window) / half_window
    assert depth == pytest.approx(expected, rel=0.1)
    assert (amplitudes.max() - amplitudes.min()) / amplitudes.mean() == pytest.approx(
        2 * expected, rel=0.2)
    assert math.remainder(phase - ecc.phase_rad, 2 * math.pi) == pytest.approx(0.0, abs=0.1)
    plain = _heavy_disk(derive_unit("SN123", effects=()), disk)
    assert _once_per_revolution(*_order1_over_a_revolution(plain, hz, periods))[0] < 0.1 * depth


def test_below_the_rotors_mode_the_spring_scales_like_the_torque_and_hides_eccentricity() -> None:
    """The ripple's torque and the magnetic spring that turns it into motion are both
    airgap torque: while the spring dominates, their ratio, the motion, barely varies."""
    unit = _heavy_disk(derive_unit("SN123", effects=[Effect.ROTOR_ECCENTRICITY]), 2.5e-5)
    ecc = unit.motor.eccentricity
    assert ecc is not None
    depth, _ = _once_per_revolution(*_order1_over_a_revolution(unit, 20.0, 5))
    assert depth < 0.2 * ecc.relative


def _at_angle_zero(plant: Plant) -> None:
    """The rotor put at a mechanical angle of 0, at rest, the drive off."""
    plant.place_on_trajectory(
        DriveCommand(False, 0.0, Trims(), STAIRCASE_LAG_MICROSTEPS, 0.0, 0.0, M))
    assert plant.rotor_angle_rad == 0.0


def test_an_unbalanced_rotor_creeps_towards_its_low_point_when_the_drive_is_off() -> None:
    unit = derive_unit("SN123", effects=[Effect.ROTOR_ECCENTRICITY])
    ecc = unit.motor.eccentricity
    assert ecc is not None
    plant = Plant(unit)
    _at_angle_zero(plant)
    for _ in range(200):
        plant.advance(DriveCommand(False, 0.0, Trims(), 0.0, 0.0, 0.0, M))
    # Gravity's torque −U·sin(θ + ψ) turns the rotor towards θ = −ψ.
    expected_direction = -math.copysign(1.0, math.sin(ecc.unbalance_phase_rad))
    assert plant.rotor_angle_rad * expected_direction > 0
    assert abs(plant.rotor_angle_rad) < math.radians(5)


@pytest.mark.parametrize("seed", [539493919, 1257966784, 449235291])
def test_an_unbalanced_rotor_arrives_at_rest_where_gravity_and_detent_balance(seed: int) -> None:
    # Wide-population units whose rotors, started at an angle of 0 without bearing
    # friction, swung at standstill (0.2-9.9 m/s² rms) and failed the sensor's self-check.
    unit = draw_line_unit(seed).unit
    ecc = unit.motor.eccentricity
    assert ecc is not None and ecc.unbalance_Nm > 0
    unit = replace(unit, sensor=replace(unit.sensor, noise_density_ug=0.0))
    plant = Plant(unit)
    start = plant.rotor_angle_rad
    # A balance, and a stable one: the static torque falls through zero there.
    static = [float(torque(start + d, 0.0, 0.0, unit.motor))
              - ecc.unbalance_Nm * math.sin(start + d + ecc.unbalance_phase_rad)
              for d in (-1e-6, 0.0, 1e-6)]
    assert abs(static[1]) < 1e-9 * unit.motor.holding_torque_Nm(1.0)
    assert static[0] > 0 > static[2]
    tangential = []
    for _ in range(300):
        plant.advance(DriveCommand(False, 0.0, Trims(), 0.0, 0.0, 0.0, M))
        tangential.append(plant.sensor_reading_mps2[unit.sensor.tangential_axis.column])
    assert abs(plant.rotor_angle_rad - start) < 1e-6
    assert float(np.std(tangential)) < 1e-3


def test_the_unbalance_is_a_load_not_motor_torque() -> None:
    unit = replace(derive_unit("SN3002", effects=()), amplifier=AmplifierParams())
    # No bearing friction, whose implicit treatment would share in the first step.
    bearing = replace(unit.mechanics.rotor_bearing, coulomb_pos_Nm=0.0, coulomb_neg_Nm=0.0,
                      viscous_Nms=0.0)
    unit = replace(unit, mechanics=replace(unit.mechanics, rotor_bearing=bearing))
    motor = replace(unit.motor, eccentricity=Eccentricity(0.0, 0.0, 0.01, 0.4))
    plant = Plant(replace(unit, motor=motor), sync_period_s=1e-4, substeps=1)
    _at_angle_zero(plant)
    plant.advance(DriveCommand(True, 1000.0, Trims(), 100.5, 0.0, 0.0, M))
    i_a, i_b = plant.phase_currents_A
    assert plant.motor_torque_Nm == pytest.approx(float(torque(0.0, i_a, i_b, motor)), abs=1e-12)
    # The rotor started at rest at 0: only motor torque and −U·sin(0.4) moved it.
    j = unit.motor.rotor_inertia_kgm2 + unit.mechanics.disk.inertia_kgm2  # type: ignore[union-attr]
    no_unbalance = Plant(unit, sync_period_s=1e-4, substeps=1)
    _at_angle_zero(no_unbalance)
    no_unbalance.advance(DriveCommand(True, 1000.0, Trims(), 100.5, 0.0, 0.0, M))
    dv = plant.rotor_velocity_rad_s - no_unbalance.rotor_velocity_rad_s
    assert dv == pytest.approx(-0.01 * math.sin(0.4) * 1e-4 / j, rel=1e-9)


def test_the_truth_gives_the_eccentricity_and_its_unbalance() -> None:
    unit = derive_unit("SN3003", load=LoadKind.BELT, effects=[Effect.ROTOR_ECCENTRICITY])
    truth = json.loads(json.dumps(unit_truth(unit)))
    (entry,) = truth["effects"]
    assert entry["id"] == "rotor_eccentricity"
    assert entry["parameters"]["relative"] == unit.motor.eccentricity.relative  # type: ignore[union-attr]
    assert {"phase_rad", "unbalance_Nm", "unbalance_phase_rad", "law"} <= set(entry["parameters"])


def test_an_eccentric_rotor_is_refused_an_eccentricity_beyond_the_airgap() -> None:
    with pytest.raises(ValueError, match="eccentricity"):
        Eccentricity(1.2, 0.0)
    with pytest.raises(ValueError, match="unbalance"):
        Eccentricity(0.05, 0.0, -1.0)
