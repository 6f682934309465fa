"""Out-of-vocabulary sensor imperfections: a nonlinear element, a tilted mounting."""

from __future__ import annotations

import json
import math
from dataclasses import replace

import numpy as np
import pytest

from station.core import STANDARD_GRAVITY, Effect, Trims
from station.dsp.demod import harmonic_phasors
from station.physics.params import (
    AmplifierParams,
    DiskParams,
    SensorParams,
    UnitParams,
    UnnamedEffect,
    derive_unit,
)
from station.physics.plant import DriveCommand, Plant
from station.physics.truth import unit_truth

M = 256
T = 0.001
HZ = 20.0


def _base() -> UnitParams:
    unit = derive_unit("SN123", effects=())
    return replace(unit, amplifier=AmplifierParams(),
                   sensor=replace(unit.sensor, noise_density_ug=0.0))


def _with_sensor(unit: UnitParams, *, tilt_rad: float = 0.0, nonlinearity_c2: float = 0.0,
                 nonlinearity_c3: float = 0.0) -> UnitParams:
    sensor = replace(unit.sensor, tilt_rad=tilt_rad, nonlinearity_c2=nonlinearity_c2,
                     nonlinearity_c3=nonlinearity_c3)
    return replace(unit, sensor=sensor)


def _steady_readings(unit: UnitParams, *, range_g: int = 2, offset_mA: float = 150.0,
                     settle: int = 300, samples: int = 500) -> tuple[np.ndarray, np.ndarray]:
    """Noise-free X, Y, Z readings at 20 Hz with an offset (an order-1 ripple), after
    the transient, and the drive's electrical angle at each sample."""
    plant = Plant(unit)
    plant.set_sensor_range(range_g)
    velocity = HZ * 4 * M
    trims = Trims(offset_mA, 0.0)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    out = []
    for k in range(settle + samples):
        plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity, 0.0, M))
        if k >= settle:
            out.append(plant.sensor_reading_mps2)
    angle = 2 * math.pi * velocity * np.arange(settle + 1, settle + samples + 1) * T / (4 * M)
    return np.array(out), angle


def test_a_nonlinear_element_bends_each_axis_by_its_polynomial_of_the_full_scale() -> None:
    base = _base()
    straight, _ = _steady_readings(base, range_g=4)
    bent, _ = _steady_readings(_with_sensor(base, nonlinearity_c2=0.02, nonlinearity_c3=-0.01),
                               range_g=4)
    fs = 4 * STANDARD_GRAVITY
    expected = straight + 0.02 * straight**2 / fs - 0.01 * straight**3 / fs**2
    np.testing.assert_allclose(bent, expected, rtol=1e-12, atol=1e-12)
    assert bent[:, 2].mean() != pytest.approx(STANDARD_GRAVITY, abs=1e-3)


def test_sensor_nonlinearity_creates_harmonics_from_a_pure_tone() -> None:
    """cos² and cos³ of an order-1 ripple A put c2·A²/(2·FS) at order 2, c3·A³/(4·FS²) at 3.

    A heavy disk turns the offset's torque ripple into acceleration without
    the rotor swinging on its spring, so the ripple is a pure tone; a 1-m arm
    makes it large enough to bend.
    """
    base = _base()
    base = replace(base, mechanics=replace(base.mechanics, disk=DiskParams(0.1)),
                   sensor=replace(base.sensor, radius_m=1.0))
    c2, c3 = 0.02, 0.01
    straight, angle = _steady_readings(base, offset_mA=400.0, settle=2000)
    bent, _ = _steady_readings(_with_sensor(base, nonlinearity_c2=c2, nonlinearity_c3=c3),
                               offset_mA=400.0, settle=2000)
    before = harmonic_phasors(straight[:, 0], angle, [1, 2, 3])
    after = harmonic_phasors(bent[:, 0], angle, [1, 2, 3])
    a = abs(before[0])
    fs = 2 * STANDARD_GRAVITY
    assert abs(before[1]) < 0.002 * a and abs(before[2]) < 0.002 * a
    assert abs(after[1] - before[1]) == pytest.approx(c2 * a**2 / (2 * fs), rel=0.05)
    assert abs(after[2] - before[2]) == pytest.approx(c3 * a**3 / (4 * fs**2), rel=0.05)


def test_a_tilted_sensor_mixes_the_radial_axis_into_the_tangential_one() -> None:
    base = _base()
    alpha = math.radians(12.0)
    square, _ = _steady_readings(base)
    tilted, _ = _steady_readings(_with_sensor(base, tilt_rad=alpha))
    t, r = square[:, 0], square[:, 1]
    np.testing.assert_allclose(tilted[:, 0], math.cos(alpha) * t + math.sin(alpha) * r,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(tilted[:, 1], math.cos(alpha) * r - math.sin(alpha) * t,
                               rtol=1e-12, atol=1e-12)
    np.testing.assert_array_equal(tilted[:, 2], square[:, 2])
    # The centripetal −r·ω² now shows on the tangential axis as a steady offset.
    centripetal = -base.sensor_radius_m * (2 * math.pi * HZ / base.rotor_teeth) ** 2
    assert tilted[:, 0].mean() == pytest.approx(math.sin(alpha) * centripetal, rel=0.02)


def test_a_square_linear_sensor_is_what_it_was() -> None:
    base = _base()
    explicit = _with_sensor(base, tilt_rad=0.0, nonlinearity_c2=0.0, nonlinearity_c3=0.0)
    np.testing.assert_array_equal(_steady_readings(base)[0], _steady_readings(explicit)[0])
    assert base.unnamed_effects == frozenset()


def test_unnamed_effects_are_listed_apart_from_the_vocabulary() -> None:
    unit = _with_sensor(derive_unit("SN4", effects=[Effect.FRICTION]), tilt_rad=-0.2,
                        nonlinearity_c2=0.01)
    truth = json.loads(json.dumps(unit_truth(unit)))
    assert [e["id"] for e in truth["effects"]] == ["friction"]
    listed = {e["id"]: e["parameters"] for e in truth["out_of_vocabulary"]}
    assert set(listed) == {"sensor_nonlinearity", "sensor_tilt"}
    assert listed["sensor_tilt"]["tilt_rad"] == -0.2
    assert listed["sensor_nonlinearity"]["c2"] == 0.01
    assert not {u.value for u in UnnamedEffect} & {e.value for e in Effect}
    assert unit_truth(derive_unit("SN4"))["out_of_vocabulary"] == []


def test_implausible_sensor_imperfections_are_refused() -> None:
    with pytest.raises(ValueError, match="45"):
        SensorParams(radius_m=0.04, tilt_rad=1.0)
    with pytest.raises(ValueError, match="nonlinearity"):
        SensorParams(radius_m=0.04, nonlinearity_c2=0.4, nonlinearity_c3=0.2)
