"""Flux harmonics: the mutual inductances' higher orders, which turn a sine-cosine drive's
torque into ripple at 2 to 5 times the electrical frequency, growing with the current."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import harmonic_pairs, sigmas
from station.diagnosis.hooks import Grid, Hooks, Params, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations

FLUX_ORDERS = (2, 3, 4, 5)
"""Harmonics j of the mutual inductances L1f, L2f (j = 1 is the fundamental)."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # Harmonics of L1f, L2f relative to Lm1: a few percent on real motors.
    return [Block("flux", 4 * len(FLUX_ORDERS), 0.0, -0.25, 0.25, BlockKind.LINEAR)]


def magnet(model: Model, p: Params, m: Motion, pa: Grid, pb: Grid) -> tuple[Grid, Grid]:
    # ∂L/∂θ of each harmonic of the mutual inductances, phase B a quarter period on.
    c = model.block(p, "flux")
    for i, j in enumerate(FLUX_ORDERS):
        ca, sa = m.harmonic(j)
        cb, sb = m.harmonic(j, 1)
        pa = pa - j * (c[4 * i] * sa + c[4 * i + 1] * ca)
        pb = pb - j * (c[4 * i + 2] * sb + c[4 * i + 3] * cb)
    return pa, pb


def magnet_slope(model: Model, p: Params, m: Motion, da: Grid, db: Grid
                 ) -> tuple[Grid, Grid]:
    c = model.block(p, "flux")
    for i, j in enumerate(FLUX_ORDERS):
        ca, sa = m.harmonic(j)
        cb, sb = m.harmonic(j, 1)
        da = da - j * j * (c[4 * i] * ca - c[4 * i + 1] * sa)
        db = db - j * j * (c[4 * i + 2] * cb - c[4 * i + 3] * sb)
    return da, db


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    scale = parts.modulation * parts.kt
    out: list[Grid] = []
    for j in FLUX_ORDERS:
        ca, sa = m.harmonic(j)
        cb, sb = m.harmonic(j, 1)
        out += [-j * scale * m.i_a * sa, -j * scale * m.i_a * ca,
                -j * scale * m.i_b * sb, -j * scale * m.i_b * cb]
    return out


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    return harmonic_pairs(fit, sigmas(cov), "flux", FLUX_ORDERS, scale=100.0,
                          key="relative_to_Lm1_percent")


TERMS = EffectTerms(
    effect=Effect.FLUX_HARMONICS,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Nothing kept: a real motor has some, but what a 1 A characterization resolves is "
        "ripple the customer feels and the compensation table removes, so it is named."),
    rivals={
        Effect.CURRENT_DISTORTION: (
            "record the phase currents (drive current sense or a current probe) while "
            "running: distortion shows in the current waveform, flux harmonics do not; or "
            "back-drive the motor with the drive disabled and record the back-EMF, whose "
            "harmonics are the flux's"),
        Effect.DETENT_TORQUE: (
            "repeat the characterization at more currents including a low one: cogging "
            "torque does not change with current, flux-harmonic torque grows with it"),
    },
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("flux",)}, magnet=magnet, magnet_slope=magnet_slope,
                bases=bases),
)
