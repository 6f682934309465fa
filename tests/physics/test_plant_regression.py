"""Units without saturation, eccentricity or unnamed sensor physics run as they always did."""

from __future__ import annotations

import hashlib
from dataclasses import replace

import pytest

from station.core import Effect, LoadKind, Trims
from station.physics.params import UnitParams, derive_unit
from station.physics.plant import DriveCommand, Plant

M = 256
T = 0.001
EARLIER_EFFECTS = (
    Effect.FLUX_HARMONICS,
    Effect.DETENT_TORQUE,
    Effect.RELUCTANCE_TORQUE,
    Effect.LOAD_RESONANCE,
    Effect.CURRENT_DISTORTION,
    Effect.CURRENT_LOOP_LAG,
    Effect.FRICTION,
    Effect.SENSOR_CLOCK_DRIFT,
)
"""The vocabulary before magnetic_saturation and rotor_eccentricity joined it."""

RECORDED = {
    (LoadKind.DISK, False): "4debcfec0d137fed",
    (LoadKind.DISK, True): "c73e9f52967acee7",
    (LoadKind.BELT, False): "3d64f6edcfc783b6",
    (LoadKind.BELT, True): "cb7ac3a331d245e6",
}
"""SHA-256 (first 16 hex digits) of 1000 SYNCs of counts, taken with the plant as it
was before the new effects (taken again when the sensor's reading moved half a substep
to the acceleration's own instant, which changes every run). Counts are rounded to the
LSB, so a last-bit difference in a platform's libm does not show; a change of the physics
does."""


def _counts_digest(unit: UnitParams) -> str:
    plant = Plant(unit, seed=7)
    velocity = 20.0 * 4 * M
    trims = Trims(40.0, -25.0, 10400.0, 9600.0)
    plant.place_on_trajectory(DriveCommand(True, 1000.0, trims, 0.0, velocity, 0.0, M))
    digest = hashlib.sha256()
    for k in range(1000):
        counts = plant.advance(DriveCommand(True, 1000.0, trims, velocity * k * T, velocity,
                                            0.0, M))
        digest.update(repr(counts).encode())
    return digest.hexdigest()[:16]


@pytest.mark.parametrize(("load", "earlier"), list(RECORDED))
def test_units_without_the_new_physics_run_bit_for_bit_as_before_it_existed(
        load: LoadKind, earlier: bool) -> None:
    unit = derive_unit("SN4242", load=load, effects=EARLIER_EFFECTS if earlier else ())
    assert _counts_digest(unit) == RECORDED[(load, earlier)]


def test_switching_the_new_physics_off_again_restores_the_same_run() -> None:
    every = derive_unit("SN4242", load=LoadKind.BELT, effects=list(Effect))
    off = replace(
        every,
        motor=replace(every.motor, saturation_current_A=None, eccentricity=None),
        effects=every.effects - {Effect.MAGNETIC_SATURATION, Effect.ROTOR_ECCENTRICITY},
    )
    assert off == derive_unit("SN4242", load=LoadKind.BELT, effects=EARLIER_EFFECTS)
    assert _counts_digest(off) == RECORDED[(LoadKind.BELT, True)]
    assert _counts_digest(every) != RECORDED[(LoadKind.BELT, True)]
