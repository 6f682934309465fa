"""Rotor eccentricity: an airgap that varies once per mechanical revolution, modulating the
magnet's torque, and the load an off-centre mass puts on the rotor."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import pair, sigmas
from station.diagnosis.hooks import Grid, Hooks, Params, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations

UNBALANCE_MAX = 0.3
"""The once-per-revolution load's bound, a fraction of the holding torque at the largest
current: a third of what holds the rotor is no unbalance a unit would be shipped with."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # The airgap's modulation of the motor's torque, and the load the off-centre mass
    # puts on the rotor: CLI.md's "torque or load periodic once per mechanical revolution".
    return [Block("eccentricity", 2, 0.0, -0.3, 0.3, BlockKind.LINEAR),
            Block("unbalance", 2, 0.0, -UNBALANCE_MAX, UNBALANCE_MAX, rejects=(-1, 1))]


def modulation(model: Model, p: Params) -> NDArray[np.float64]:
    """1 + ε·cos(θ + φ) averaged over each segment's mechanical angles, (S, 1)."""
    e = model.block(p, "eccentricity")
    mech = model.obs.mechanical
    out: NDArray[np.float64] = (1.0 + e[0] * mech.real - e[1] * mech.imag)[:, None]
    return out


def load(model: Model, p: Params) -> NDArray[np.float64]:
    """The off-centre rotor's load, U·sin(θ + φ) averaged over each segment's mechanical
    angles (Kt units, (S,)), with U·cos φ and U·sin φ as fractions of the holding torque
    at the largest current.

    Within one electrical period it is a constant load: it moves the rotor along its
    magnetic spring, and with it every harmonic's phase (order times the slip), from one
    trim step to the next as the rotor turns through its revolution."""
    u = model.block(p, "unbalance") * model.largest_A
    mech = model.obs.mechanical
    out: NDArray[np.float64] = u[0] * mech.imag + u[1] * mech.real
    return out


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    mech = model.obs.mechanical[:, None]
    return [mech.real * parts.inner, -mech.imag * parts.inner]


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sig = sigmas(cov)
    sl = fit.model.layout.slices["eccentricity"]
    modulation = pair(fit.params[sl], sig[sl], 100.0)
    out = {"torque_modulation_percent": modulation["magnitude"],
           "sigma_percent": modulation["sigma"], "phase_rad": modulation["phase_rad"],
           "note": "once per mechanical revolution of the rotor, on the magnet's torque"}
    if fit.model.layout.has("unbalance"):
        sl = fit.model.layout.slices["unbalance"]
        # (U·cos φ, U·sin φ) of the load U·sin(θ + φ): φ is the pair's own phase.
        load = pair(fit.params[sl], sig[sl], 100.0)
        out.update({
            "unbalance_load_percent": load["magnitude"],
            "unbalance_sigma_percent": load["sigma"],
            "unbalance_phase_rad": load["phase_rad"],
            "unbalance_note": ("load U·sin(θ + φ) on the rotor, θ its mechanical angle, U in "
                               "percent of the holding torque at the largest current"),
        })
    return out


TERMS = EffectTerms(
    effect=Effect.ROTOR_ECCENTRICITY,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Nothing kept: some runout is in every rotor, but named only when the "
        "once-per-revolution terms beat themselves fitted at wrong angles."),
    rivals={
        Effect.SENSOR_CLOCK_DRIFT: (
            "hold one condition for several mechanical revolutions: eccentricity repeats "
            "with the rotor's angle, a drifting clock with time"),
    },
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("eccentricity",), Role.LOAD: ("unbalance",)},
                modulation=modulation, load=load, bases=bases),
)
