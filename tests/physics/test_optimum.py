"""Optimal trims and steady harmonics, and what each effect does to them."""

from __future__ import annotations

import itertools
import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import GAIN_UNITY, Effect, LoadKind, Trims
from station.dsp import harmonic_phasors
from station.physics.motor import torque
from station.physics.optimum import (
    STEADY_PERIODS,
    amplifier_optimum,
    optimal_trims,
    revolution_periods,
    steady_harmonics,
    steady_reading,
)
from station.physics.params import UnitParams, derive_unit
from station.physics.plant import DriveCommand, Plant
from station.sim.population import draw_line_unit

M = 256
T = 0.001
RECORD_SAMPLES = 10_000
"""A 10-s record at 1 kHz: what 'measurable' is judged against."""


def _load_angle(unit: UnitParams, velocity: float) -> float:
    """Mean electrical lag of the rotor behind the field in steady motion."""
    plant = Plant(replace(unit, sensor=replace(unit.sensor, noise_density_ug=0.0)))
    plant.place_on_trajectory(DriveCommand(True, 1000.0, Trims(), 0.0, velocity, 0.0, M))
    lags = []
    for n in range(600):
        plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0, M))
        if n >= 300:
            x_end = 2 * math.pi * velocity * (n + 1) * T / (4 * M)
            lags.append(x_end - unit.rotor_teeth * plant.rotor_angle_rad)
    return float(np.mean(lags))


@pytest.mark.parametrize("load", [LoadKind.DISK, LoadKind.BELT])
def test_without_effects_the_optimum_exactly_undoes_the_amplifier(load: LoadKind) -> None:
    unit = derive_unit("SN123", load=load, effects=())
    found = optimal_trims(unit)
    ideal = amplifier_optimum(unit)
    assert found.offset_a_mA == pytest.approx(ideal.offset_a_mA, abs=0.5)
    assert found.offset_b_mA == pytest.approx(ideal.offset_b_mA, abs=0.5)
    assert found.gain_a == pytest.approx(ideal.gain_a, abs=1.0)
    assert found.gain_a + found.gain_b == pytest.approx(2 * GAIN_UNITY)


def test_the_optimum_is_deterministic() -> None:
    unit = derive_unit("SN2024", effects=list(Effect))
    assert optimal_trims(unit) == optimal_trims(unit)


@pytest.mark.parametrize("load", [LoadKind.DISK, LoadKind.BELT])
def test_optimum_with_every_effect_nulls_h1_and_minimises_h2(load: LoadKind) -> None:
    unit = derive_unit("SN808", load=load, effects=list(Effect))
    found = optimal_trims(unit)
    nominal = steady_harmonics(unit, Trims())
    best = steady_harmonics(unit, found)
    assert abs(best[0]) < 1e-3 * abs(nominal[0])
    for ds in (-30.0, 30.0):
        off = replace(found, gain_a=found.gain_a + ds, gain_b=found.gain_b - ds)
        assert abs(steady_harmonics(unit, off)[1]) > abs(best[1])


def test_flux_harmonics_leave_the_residual_offsets_and_gains_the_paper_saw() -> None:
    shifts = []
    for serial in ("SN1", "SN2", "SN3", "SN4"):
        unit = derive_unit(serial, effects=[Effect.FLUX_HARMONICS])
        found, ideal = optimal_trims(unit), amplifier_optimum(unit)
        shifts.append((math.hypot(found.offset_a_mA - ideal.offset_a_mA,
                                  found.offset_b_mA - ideal.offset_b_mA),
                       abs(found.gain_a - ideal.gain_a)))
    offsets, gains = zip(*shifts, strict=True)
    assert min(offsets) > 1.0 and max(offsets) < 40.0  # several mA
    assert max(gains) > 10.0 and max(gains) < 300.0  # tens of gain units


def test_plant_h1_null_matches_the_torque_model_null() -> None:
    """Eq. (1) at the plant's own load angle predicts where the plant's H1 vanishes."""
    unit = derive_unit("SN3", effects=[Effect.FLUX_HARMONICS])
    found = optimal_trims(unit)
    velocity = 20.0 * 4 * M
    rho = _load_angle(unit, velocity)
    x = np.arange(720) * 2 * math.pi / 720
    theta = (x - rho) / unit.rotor_teeth
    amp = unit.amplifier

    def torque_h1(net_a: float, net_b: float) -> complex:
        i_a = net_a + (1 + amp.gain_error_a) * found.gain_a / GAIN_UNITY * np.cos(x)
        i_b = net_b + (1 + amp.gain_error_b) * found.gain_b / GAIN_UNITY * np.sin(x)
        return complex(np.fft.rfft(torque(theta, i_a, i_b, unit.motor))[1] * 2 / x.size)

    base = torque_h1(0.0, 0.0)
    da, db = torque_h1(0.01, 0.0) - base, torque_h1(0.0, 0.01) - base
    jac = np.array([[da.real, db.real], [da.imag, db.imag]]) / 0.01
    predicted = np.linalg.solve(jac, -np.array([base.real, base.imag])) * 1000
    net = np.array([found.offset_a_mA + amp.offset_a_mA, found.offset_b_mA + amp.offset_b_mA])
    assert np.hypot(*predicted) > 1.0
    np.testing.assert_allclose(net, predicted, atol=1.0)


@pytest.mark.parametrize("effect", [e for e in Effect if e is not Effect.SENSOR_CLOCK_DRIFT])
def test_each_effect_changes_the_ripple_measurably(effect: Effect) -> None:
    """Some harmonic moves by more than ten noise σ of a 10-s record's demodulation, as
    a hold of four periods sees it (an eccentric rotor's sidebands, a harmonic there,
    average out over a revolution)."""
    plain = derive_unit("SN123", effects=())
    with_effect = derive_unit("SN123", effects=[effect])
    with_effect = replace(with_effect, sensor=replace(with_effect.sensor, sample_phase=0.5))
    trims = Trims(0.0, 0.0, 10500.0, 9500.0)
    orders = (1, 2, 3, 4)
    before = steady_harmonics(plain, trims, orders=orders, periods=STEADY_PERIODS)
    after = steady_harmonics(with_effect, trims, orders=orders, periods=STEADY_PERIODS)
    floor = plain.sensor.noise_sigma_mps2() * math.sqrt(2 / RECORD_SAMPLES)
    assert np.max(np.abs(after - before)) > 10 * floor


def test_the_plants_ripple_and_optimum_are_not_its_sensors_clock() -> None:
    # A drifting sample clock changes what the sensor reports, not the ripple the trims
    # null: sampled late, a repeated sample leaked orders 4-12 of a rough unit into
    # orders 1 and 2 and put its "optimum" 43 mA from the plant's (population 335014438).
    plain = derive_unit("SN123", effects=[Effect.FLUX_HARMONICS])
    drifting = derive_unit("SN123", effects=[Effect.FLUX_HARMONICS, Effect.SENSOR_CLOCK_DRIFT])
    assert drifting.sensor.clock_drift_ppm != 0.0
    trims = Trims(30.0, -20.0, 10500.0, 9500.0)
    np.testing.assert_array_equal(steady_harmonics(drifting, trims),
                                  steady_harmonics(plain, trims))
    assert optimal_trims(drifting) == optimal_trims(plain)


def test_detent_shows_at_the_fourth_harmonic() -> None:
    unit = derive_unit("SN5", effects=())
    calibrated = amplifier_optimum(unit)
    plain = steady_harmonics(unit, calibrated, orders=(4,))
    detent = steady_harmonics(derive_unit("SN5", effects=[Effect.DETENT_TORQUE]), calibrated,
                              orders=(4,))
    assert abs(detent[0]) > 100 * abs(plain[0])
    assert abs(detent[0]) > 0.5  # m/s²


def test_current_distortion_moves_the_optimum() -> None:
    unit = derive_unit("SN6", effects=[Effect.CURRENT_DISTORTION])
    found, ideal = optimal_trims(unit), amplifier_optimum(unit)
    assert math.hypot(found.offset_a_mA - ideal.offset_a_mA,
                      found.offset_b_mA - ideal.offset_b_mA) > 1.0


def test_current_loop_lag_delays_the_ripple_by_the_loop_phase() -> None:
    unit = derive_unit("SN7", effects=[Effect.CURRENT_LOOP_LAG])
    plain = derive_unit("SN7", effects=())
    f = 20.0
    shift = np.angle(steady_harmonics(unit, Trims(), orders=(1,))[0]
                     / steady_harmonics(plain, Trims(), orders=(1,))[0])
    bw = 0.5 * (unit.amplifier.bandwidth_a_hz + unit.amplifier.bandwidth_b_hz)  # type: ignore[operator]
    assert shift == pytest.approx(-math.atan(f / bw), rel=0.15)


def test_friction_lags_the_rotor_and_differs_with_direction() -> None:
    velocity = 20.0 * 4 * M
    serial = next(f"SN{n}" for n in range(100, 200) if _friction_asymmetry(f"SN{n}") > 0.2)
    plain = derive_unit(serial, effects=())
    rough = derive_unit(serial, effects=[Effect.FRICTION])
    forward, backward = _load_angle(rough, velocity), -_load_angle(rough, -velocity)
    assert forward > _load_angle(plain, velocity) + math.radians(3)
    asymmetry_plain = abs(_load_angle(plain, velocity) + _load_angle(plain, -velocity))
    assert abs(forward - backward) > 5 * asymmetry_plain
    friction = rough.mechanics.load_friction
    assert friction is not None
    coulomb = friction.coulomb_pos_Nm, friction.coulomb_neg_Nm
    assert (forward > backward) == (coulomb[0] > coulomb[1])


def _friction_asymmetry(serial: str) -> float:
    friction = derive_unit(serial, effects=[Effect.FRICTION]).mechanics.load_friction
    assert friction is not None
    return abs(friction.coulomb_pos_Nm / friction.coulomb_neg_Nm - 1)


@pytest.mark.parametrize("ppm", [300.0, -300.0])
def test_a_drifting_sensor_clock_repeats_or_skips_samples(ppm: float) -> None:
    base = derive_unit("SN9", effects=[Effect.SENSOR_CLOCK_DRIFT])
    unit = replace(base, sensor=replace(base.sensor, clock_drift_ppm=ppm, sample_phase=0.5))
    plant = Plant(unit)
    velocity = 20.0 * 4 * M
    counts = [plant.advance(DriveCommand(True, 1000.0, Trims(), velocity * n * T, velocity, 0.0,
                                         M)) for n in range(10_000)]
    repeats = sum(a == b for a, b in itertools.pairwise(counts))
    # Noise makes consecutive distinct samples differ; a repeat is the same sample twice.
    expected = 10_000 * ppm * 1e-6 if ppm > 0 else 0
    assert repeats == pytest.approx(expected, abs=1)


def test_an_optimum_without_current_is_refused() -> None:
    with pytest.raises(ValueError, match="positive"):
        optimal_trims(derive_unit("SN1", effects=()), amplitude_mA=0.0)


@pytest.mark.parametrize("load", [LoadKind.DISK, LoadKind.BELT])
def test_plant_h1_vanishes_at_zero_net_offset_with_balanced_gains(load: LoadKind) -> None:
    unit = derive_unit("SN31", load=load, effects=())
    nominal = steady_harmonics(unit, Trims())
    compensated = steady_harmonics(unit, amplifier_optimum(unit))
    assert abs(compensated[0]) < 1e-4 * abs(nominal[0])
    assert abs(compensated[1]) < 1e-3 * abs(nominal[1])


def test_harmonics_at_a_frequency_off_the_sync_grid_still_span_whole_periods() -> None:
    """At 30 Hz a 4-period window would be 133.3 samples and leak H4 into H1."""
    unit = derive_unit("SN31", effects=[Effect.DETENT_TORQUE])
    compensated = steady_harmonics(unit, amplifier_optimum(unit), electrical_hz=30.0,
                                   orders=(1, 4))
    assert abs(compensated[1]) > 0.1
    assert abs(compensated[0]) < 1e-4 * abs(compensated[1])


@pytest.mark.parametrize("seed", [170, 576, 956725264])
def test_a_rough_unit_far_from_the_nominal_trims_still_converges(seed: int) -> None:
    # Population seed 170: offsets near 210 mA, a gain split near 1,000 units, detent, flux
    # harmonics and a coupling. Chord steps on the Jacobian taken at the nominal trims
    # alternated about the optimum, halving each time, and ran out of iterations. Seed 576
    # (a belt; detent, flux, reluctance, a lagging loop): slopes over 200 gain units
    # overshot the split's optimum twice over, in a cycle that never closed. Seed
    # 956725264 (phase gains 27 % apart, beyond any recipe's bounds): the first step from
    # the nominal trims went 14,000 gain units the wrong way.
    unit = draw_line_unit(seed).unit
    found = optimal_trims(unit)
    assert abs(found.offset_a_mA) > 100 and abs(found.gain_a - GAIN_UNITY) > 500
    h = steady_harmonics(unit, found)
    assert abs(h[0]) < 1e-3


def test_an_eccentric_rotors_optimum_nulls_what_no_rotor_angle_changes() -> None:
    # Its airgap turns with it: over four periods a harmonic holds sidebands at the rotor's
    # frequency, by where the rotor is; over a revolution they average out, and what is
    # left is what the trims can null (population seed 1136781479: 13 mA between the two).
    unit = derive_unit("SN123", effects=[Effect.ROTOR_ECCENTRICITY])
    assert revolution_periods(unit) == unit.rotor_teeth
    assert revolution_periods(derive_unit("SN123", effects=())) == STEADY_PERIODS
    best = optimal_trims(unit)
    reading, angle = steady_reading(unit, best)
    tangential = reading[:, unit.sensor.tangential_axis.column]
    chunk = 4 * 50  # four periods at 20 Hz and 1 kHz
    parts = [abs(harmonic_phasors(tangential[i:i + chunk], angle[i:i + chunk], (1,))[0])
             for i in range(0, tangential.size, chunk)]
    assert len(parts) == unit.rotor_teeth // 4 + 1
    assert abs(steady_harmonics(unit, best)[0]) < 1e-3
    assert max(parts) > 20 * abs(steady_harmonics(unit, best)[0])
