"""The time-stepped plant: dynamics, drive currents and the sensor's front end."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import GAIN_UNITY, SATURATED_COUNTS, STANDARD_GRAVITY, Effect, LoadKind, Trims
from station.dsp.demod import harmonic_phasors
from station.physics.motor import magnetic_stiffness, torque
from station.physics.params import (
    AmplifierParams,
    FrictionParams,
    UnitParams,
    derive_unit,
)
from station.physics.plant import (
    STAIRCASE_LAG_MICROSTEPS,
    DriveCommand,
    Plant,
    commanded_currents_A,
    modal_analysis,
)
from station.sim.population import draw_unit

M = 256
T = 0.001


def _quiet(unit: UnitParams) -> UnitParams:
    return replace(unit, sensor=replace(unit.sensor, noise_density_ug=0.0))


def _ideal_amplifier(unit: UnitParams) -> UnitParams:
    return replace(unit, amplifier=AmplifierParams())


NOMINAL = Trims()


def _field_angle(position: float) -> float:
    """Electrical angle of the drive's currents for a position demand (microsteps)."""
    return 2 * math.pi * (position - STAIRCASE_LAG_MICROSTEPS) / (4 * M)


def _hold(
    position: float, *, trims: Trims = NOMINAL, amplitude_mA: float = 1000.0, enabled: bool = True
) -> DriveCommand:
    return DriveCommand(enabled, amplitude_mA, trims, position, 0.0, 0.0, M)


def _run(plant: Plant, command: DriveCommand, cycles: int) -> np.ndarray:
    return np.array([plant.advance(command) for _ in range(cycles)])


def _balanced_trims(unit: UnitParams, net_a_mA: float, net_b_mA: float) -> Trims:
    """Trims that leave the given net offsets and equal actual fundamentals."""
    amp = unit.amplifier
    return Trims(
        net_a_mA - amp.offset_a_mA,
        net_b_mA - amp.offset_b_mA,
        GAIN_UNITY / (1 + amp.gain_error_a),
        GAIN_UNITY / (1 + amp.gain_error_b),
    )


def _ring_frequency_hz(unit: UnitParams) -> float:
    """Frequency of the rotor's ring after the field jumps by 16 microsteps at standstill.

    A noise-free damped sinusoid sampled at SYNC obeys x[n] = a·x[n−1] + b·x[n−2] + c
    with a = 2·r·cos(ωT), b = −r²; a least-squares fit gives ω exactly.
    """
    plant = Plant(_quiet(unit))
    _run(plant, _hold(0.0), 300)
    angles = []
    for _ in range(120):
        plant.advance(_hold(16.0))
        angles.append(plant.rotor_angle_rad)
    x = np.array(angles)
    design = np.column_stack([x[1:-1], x[:-2], np.ones(len(x) - 2)])
    a, b, _ = np.linalg.lstsq(design, x[2:], rcond=None)[0]
    return math.acos(a / (2 * math.sqrt(-b))) / (2 * math.pi * T)


def _without_bearing_coulomb(unit: UnitParams) -> UnitParams:
    bearing = unit.mechanics.rotor_bearing
    smooth = FrictionParams(0.0, 0.0, bearing.viscous_Nms, bearing.smoothing_rad_s)
    return replace(unit, mechanics=replace(unit.mechanics, rotor_bearing=smooth))


def test_disabled_rotor_at_rest_stays_exactly_at_rest() -> None:
    # Every effect but the eccentric rotor's unbalance, which gravity turns even unpowered.
    effects = [e for e in Effect if e is not Effect.ROTOR_ECCENTRICITY]
    plant = Plant(derive_unit("SN1", effects=effects))
    _run(plant, _hold(0.0, enabled=False), 500)
    assert plant.rotor_angle_rad == 0.0 and plant.rotor_velocity_rad_s == 0.0
    assert plant.phase_currents_A == (0.0, 0.0)


def test_enable_pulls_the_rotor_to_the_commanded_angle() -> None:
    unit = _ideal_amplifier(derive_unit("SN2", effects=()))
    plant = Plant(unit)
    _run(plant, _hold(0.0, enabled=False), 10)
    _run(plant, _hold(M), 500)  # one full step: 1.8°, a quarter of the electrical period
    assert plant.rotor_angle_rad == pytest.approx(_field_angle(M) / 50, abs=1e-5)
    assert plant.rotor_angle_rad == pytest.approx(math.radians(1.8), abs=math.radians(0.01))


def test_a_field_jump_beyond_half_a_period_pulls_the_rotor_the_short_way() -> None:
    unit = _ideal_amplifier(derive_unit("SN2", effects=()))
    plant = Plant(unit)
    _run(plant, _hold(3 * M), 500)  # +270° electrical is the same field as −90°
    assert plant.rotor_angle_rad == pytest.approx(
        (_field_angle(3 * M) - 2 * math.pi) / 50, abs=1e-5
    )


def test_a_positive_velocity_turns_the_rotor_forward_at_the_commanded_speed() -> None:
    unit = derive_unit("SN3", effects=())
    plant = Plant(unit)
    velocity = 20.0 * 4 * M
    for n in range(2000):
        plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M))
    commanded = 2 * math.pi * velocity * 2000 * T / (4 * M) / unit.rotor_teeth
    assert plant.rotor_angle_rad > 0
    assert plant.rotor_angle_rad == pytest.approx(commanded, abs=2 * math.pi / 50 / 4)


def test_a_profile_ramp_is_followed_through_the_acceleration_term() -> None:
    plant = Plant(derive_unit("SN3", effects=()))
    acc = 200000.0
    position = velocity = 0.0
    for _ in range(200):
        plant.advance(DriveCommand(True, 1000.0, Trims(), position, velocity, acc, M))
        position += velocity * T + 0.5 * acc * T * T
        velocity += acc * T
    expected = 2 * math.pi * position / (4 * M) / 50
    assert plant.rotor_angle_rad == pytest.approx(expected, abs=2 * math.pi / 50 / 4)


def test_plant_torque_is_eq1_of_the_motor_model_with_every_effect() -> None:
    unit = derive_unit("SN77", effects=[e for e in Effect if e is not Effect.CURRENT_LOOP_LAG])
    rng = np.random.default_rng(3)
    for _ in range(10):
        # One step per SYNC, short enough for the coupling's mode (see substeps_for).
        plant = Plant(unit, sync_period_s=1e-4, substeps=1)
        assert plant.substeps == 1
        trims = Trims(*rng.uniform(-100, 100, 2), *rng.uniform(8000, 12000, 2))
        plant.place_on_trajectory(_hold(rng.uniform(0, 5000), trims=trims))
        theta = plant.rotor_angle_rad
        position = rng.uniform(0, 5000)
        plant.advance(_hold(position, trims=trims, amplitude_mA=800.0))
        i_a, i_b = commanded_currents_A(_field_angle(position), 800.0, trims, unit.amplifier)
        # Harmonics are tabulated at 8192 points per period: errors of ~1e-8.
        assert plant.phase_currents_A == pytest.approx((float(i_a), float(i_b)), abs=1e-7)
        assert plant.motor_torque_Nm == pytest.approx(
            float(torque(theta, i_a, i_b, unit.motor)), abs=1e-7
        )


def test_acceleration_ripple_below_the_natural_frequency_follows_the_magnetic_spring() -> None:
    """|α| = ω²·|τ1| / |K − Jω² + jωc| with K = Kt·I·Nr·cos ρ, not τ1/J."""
    unit = _quiet(derive_unit("SN123", effects=()))
    trims = _balanced_trims(unit, 100.0, 0.0)
    velocity = 20.0 * 4 * M
    plant = Plant(unit)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    settle, n = 400, 500
    acc, lag = [], []
    for k in range(settle + n):
        plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity, 0.0, M))
        if k >= settle:
            acc.append(plant.sensor_reading_mps2[0])
            x_end = 2 * math.pi * velocity * (k + 1) * T / (4 * M)
            lag.append(x_end - unit.rotor_teeth * plant.rotor_angle_rad)
    angle = 2 * math.pi * velocity * np.arange(settle + 1, settle + n + 1) * T / (4 * M)
    measured = abs(harmonic_phasors(np.array(acc), angle, [1])[0])
    rho = float(np.mean(lag))
    j = unit.motor.rotor_inertia_kgm2 + unit.mechanics.disk.inertia_kgm2  # type: ignore[union-attr]
    k_mag = magnetic_stiffness(unit.motor, 1000.0, rho)
    assert k_mag == pytest.approx(unit.motor.kt_Nm_per_A * 1.0 * 50 * math.cos(rho))
    w = 2 * math.pi * 20.0
    c = unit.mechanics.rotor_bearing.viscous_Nms
    tau1 = unit.motor.kt_Nm_per_A * 0.100
    predicted = unit.sensor_radius_m * w * w * tau1 / abs(k_mag - j * w * w + 1j * w * c)
    assert measured == pytest.approx(predicted, rel=0.10)
    assert measured < 0.1 * unit.sensor_radius_m * tau1 / j


def test_rotor_rings_at_the_modal_frequency_and_reluctance_stiffens_it() -> None:
    plain = _without_bearing_coulomb(_ideal_amplifier(derive_unit("SN123", effects=())))
    stiff = _without_bearing_coulomb(
        _ideal_amplifier(derive_unit("SN123", effects=[Effect.RELUCTANCE_TORQUE]))
    )
    for unit in (plain, stiff):
        mode = modal_analysis(unit, 1000.0)[0]
        damped = mode.frequency_hz * math.sqrt(1 - mode.damping_ratio**2)
        assert _ring_frequency_hz(unit) == pytest.approx(damped, rel=0.01)
    assert _ring_frequency_hz(stiff) > 1.02 * _ring_frequency_hz(plain)


def test_standstill_enabled_reads_one_g_on_z_and_nothing_tangential() -> None:
    plant = Plant(derive_unit("SN9", effects=()))
    _run(plant, _hold(0.0), 500)
    counts = _run(plant, _hold(0.0), 2000)
    mean = counts.mean(axis=0) * plant.sensor_lsb_mps2()
    assert mean[2] == pytest.approx(STANDARD_GRAVITY, abs=0.01)
    assert abs(mean[0]) < 0.01 and abs(mean[1]) < 0.01


@pytest.mark.parametrize("range_g", [2, 4, 8, 16])
def test_one_lsb_is_range_times_g_over_32768(range_g: int) -> None:
    plant = Plant(_quiet(derive_unit("SN9")))
    plant.set_sensor_range(range_g)
    assert plant.sensor_lsb_mps2() == range_g * 9.80665 / 32768
    x, y, z = plant.advance(_hold(0.0, enabled=False))
    assert (x, y, z) == (0, 0, 32768 // range_g)


def test_counts_are_the_reading_rounded_to_the_lsb() -> None:
    unit = _quiet(derive_unit("SN10", effects=()))
    plant = Plant(unit)
    velocity = 20.0 * 4 * M
    plant.place_on_trajectory(DriveCommand(True, 1000.0, Trims(), 0.0, velocity, 0.0, M))
    for n in range(300):
        counts = plant.advance(
            DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M)
        )
        reading = plant.sensor_reading_mps2
        for c, r in zip(counts, reading, strict=True):
            assert c == round(r / plant.sensor_lsb_mps2())


def test_an_unknown_range_is_refused() -> None:
    with pytest.raises(ValueError, match="range"):
        Plant(derive_unit("SN9")).set_sensor_range(3)


def test_sensor_saturates_at_plus_minus_32767() -> None:
    plant = Plant(derive_unit("SN11", effects=()))
    _run(plant, _hold(0.0, enabled=False), 5)
    counts = _run(plant, _hold(128.0), 100)  # half a full step: a violent pull-in
    assert counts[:, 0].max() == SATURATED_COUNTS
    assert counts[:, 0].min() == -SATURATED_COUNTS
    peak = max(abs(r) for r in _readings_during_pull_in())
    assert peak > 2 * 9.80665 * 32767 / 32768


def _readings_during_pull_in() -> list[float]:
    plant = Plant(_quiet(derive_unit("SN11", effects=())))
    _run(plant, _hold(0.0, enabled=False), 5)
    out = []
    for _ in range(100):
        plant.advance(_hold(128.0))
        out.append(plant.sensor_reading_mps2[0])
    return out


def test_noise_sigma_matches_the_density_over_the_noise_bandwidth() -> None:
    unit = derive_unit("SN12", noise_density_ug=200.0)
    plant = Plant(unit)
    counts = _run(plant, _hold(0.0, enabled=False), 20000)
    sigma = counts.std(axis=0) * plant.sensor_lsb_mps2()
    bandwidth = unit.sensor.bandwidth_hz
    enbw = math.pi * bandwidth / (4 * unit.sensor.damping_ratio)  # 2nd-order Butterworth
    expected = 200e-6 * 9.80665 * math.sqrt(enbw)
    assert sigma == pytest.approx([expected] * 3, rel=0.04)
    assert abs(counts[:, 0].mean()) < 3 * expected / plant.sensor_lsb_mps2() / math.sqrt(2000)


def test_noise_depends_on_seed_and_serial_and_nothing_else() -> None:
    unit = derive_unit("SN12")

    def noise(u: UnitParams, seed: int) -> np.ndarray:
        return _run(Plant(u, seed=seed), _hold(0.0, enabled=False), 50)

    np.testing.assert_array_equal(noise(unit, 1), noise(unit, 1))
    assert not np.array_equal(noise(unit, 1), noise(unit, 2))
    assert not np.array_equal(noise(unit, 1), noise(replace(unit, serial="SN13"), 1))


def test_current_loop_lag_is_a_first_order_response() -> None:
    unit = _quiet(_ideal_amplifier(derive_unit("SN14")))
    unit = replace(unit, amplifier=AmplifierParams(bandwidth_a_hz=600.0, bandwidth_b_hz=650.0))
    plant = Plant(unit)
    f = 200.0
    velocity = f * 4 * M
    currents, angles = [], []
    for n in range(400):
        plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M))
        if n >= 100:
            currents.append(plant.phase_currents_A)
            t_last = (n + 1 - 1 / 8) * T  # the last substep of the period
            angles.append(_field_angle(velocity * t_last))
    i = np.array(currents)
    (h_a,) = harmonic_phasors(i[:, 0], np.array(angles), [1])
    (h_b,) = harmonic_phasors(i[:, 1], np.array(angles) - math.pi / 2, [1])
    # The loop is exact for a target linear between substeps; a sinusoid's
    # linear interpolant keeps sinc²(ωh/2) of its fundamental, with no delay.
    half_step = math.pi * f * T / 8
    interpolation = (math.sin(half_step) / half_step) ** 2
    for h, bandwidth in ((h_a, 600.0), (h_b, 650.0)):
        expected = interpolation / (1 + 1j * f / bandwidth)
        assert abs(h) == pytest.approx(abs(expected), rel=1e-4)
        assert np.angle(h) == pytest.approx(np.angle(expected), abs=1e-4)


def test_steady_trajectory_start_leaves_only_the_ripple() -> None:
    unit = _quiet(derive_unit("SN15", load=LoadKind.BELT, effects=[Effect.FRICTION]))
    plant = Plant(unit)
    velocity = 20.0 * 4 * M
    plant.place_on_trajectory(DriveCommand(True, 1000.0, Trims(), 0.0, velocity, 0.0, M))
    speeds = []
    for n in range(300):
        plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M))
        speeds.append(plant.load_velocity_rad_s)
    nominal = 2 * math.pi * 20.0 / 50 / 7
    assert np.mean(speeds) == pytest.approx(nominal, rel=0.02)
    assert np.std(speeds) < 0.05 * nominal


def test_belt_load_sees_the_motor_through_the_reduction() -> None:
    unit = derive_unit("SN16", load=LoadKind.BELT, effects=())
    plant = Plant(unit)
    velocity = 4 * M * 50 / 2.0  # one motor revolution in two seconds
    for n in range(2000):
        plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M))
    _run(plant, _hold(velocity * 2.0), 3000)
    assert plant.rotor_angle_rad == pytest.approx(2 * math.pi, abs=1e-3)
    assert plant.load_angle_rad == pytest.approx(2 * math.pi / 7, abs=1e-3)


def test_the_same_commands_give_bit_identical_runs() -> None:
    unit = derive_unit("SN17", load=LoadKind.BELT, effects=list(Effect))
    runs = []
    for _ in range(2):
        plant = Plant(unit, seed=5)
        velocity = 20.0 * 4 * M
        runs.append(
            [
                plant.advance(
                    DriveCommand(True, 900.0, Trims(), velocity * n * T, velocity, 0.0, M)
                )
                for n in range(300)
            ]
        )
    assert runs[0] == runs[1]


def _ripple_phasors(unit: UnitParams, substeps: int, orders: list[int]) -> np.ndarray:
    """The sensor's tangential harmonics at 20 Hz electrical, after the ring has died."""
    trims = _balanced_trims(unit, 100.0, 30.0)
    velocity = 20.0 * 4 * M
    plant = Plant(unit, substeps=substeps)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    settle, n = 400, 500
    acc = []
    for k in range(settle + n):
        plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity, 0.0, M))
        if k >= settle:
            acc.append(plant.sensor_reading_mps2[0])
    angle = 2 * math.pi * velocity * np.arange(settle + 1, settle + n + 1) * T / (4 * M)
    return np.asarray(harmonic_phasors(np.array(acc), angle, orders))


def test_the_sensor_reads_the_acceleration_of_its_instant_whatever_the_substep() -> None:
    """The integrator's acceleration belongs to the start of its substep; held over the
    substep it would reach the sensor half a substep late, a delay that a coarse step
    makes large enough to pass for a current loop's lag beside a strong detent torque."""
    unit = _quiet(derive_unit("SN123", effects=()))
    coarse, fine = (_ripple_phasors(unit, s, [1, 2]) for s in (8, 64))
    # Half a substep of 8 per ms at 20 Hz electrical would be 7 mrad at order 1.
    # (Measured: 0.1 and 0.24 mrad at orders 1 and 2; 6.9 and 13.8 before the fix.)
    assert np.abs(np.angle(coarse / fine)).max() < 1e-3


def test_a_pulley_damped_beyond_critical_is_integrated_stably_at_the_default_substeps() -> None:
    """Benchmark trial load_resonance@1580042069: a belt's 3.8 µg·m² pulley on a damped
    belt has no mode above 359 Hz but real poles near −43,000 s⁻¹; at 8 substeps of a 1-ms
    SYNC its explicit damping overflowed the plant."""
    unit = draw_unit(1580042069, load=LoadKind.BELT, effects=frozenset({Effect.LOAD_RESONANCE}),
                     unnamed=frozenset())
    plant = Plant(unit)
    assert plant.substeps > 8
    velocity = 10.0 * 4 * M
    plant.place_on_trajectory(DriveCommand(True, 1000.0, NOMINAL, 0.0, velocity, 0.0, M))
    counts = np.array([plant.advance(DriveCommand(True, 1000.0, NOMINAL, velocity * k * T,
                                                  velocity, 0.0, M)) for k in range(300)])
    assert np.all(np.abs(counts) < SATURATED_COUNTS)
    expected = 2 * math.pi * velocity * 300 * T / (4 * M) / unit.rotor_teeth
    assert plant.rotor_angle_rad == pytest.approx(expected, abs=2 * math.pi / unit.rotor_teeth / 4)
