"""Detent (cogging) torque: the magnet pulling the teeth into line whatever the current,
repeating every full step (four times an electrical period) and at its multiples."""

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

DETENT_ORDERS = (4, 8)
"""Cogging repeats every full step: four times per electrical period, and its multiples."""


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # Cogging in Kt units (A): up to half the holding torque at 1 A.
    return [Block("detent", 2 * len(DETENT_ORDERS), 0.0, -0.5, 0.5, BlockKind.LINEAR)]


def cogging(model: Model, p: Params, m: Motion, made: Grid) -> Grid:
    c = model.block(p, "detent")
    own = np.zeros_like(m.te)
    for i, d in enumerate(DETENT_ORDERS):
        cd, sd = m.harmonic(d)
        own += c[2 * i] * sd + c[2 * i + 1] * cd
    out: Grid = made + own
    return out


def cogging_slope(model: Model, p: Params, m: Motion, slope: Grid) -> Grid:
    c = model.block(p, "detent")
    for i, d in enumerate(DETENT_ORDERS):
        cd, sd = m.harmonic(d)
        slope = slope + d * (c[2 * i] * cd - c[2 * i + 1] * sd)
    return slope


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    out: list[Grid] = []
    for d in DETENT_ORDERS:
        cd, sd = m.harmonic(d)
        out += [parts.modulation * sd, parts.modulation * cd]
    return out


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["detent"]
    v, s = fit.params[sl], sigmas(cov)[sl]
    rated = fit.model.rated_A
    out: dict[str, Any] = {}
    for i, d in enumerate(DETENT_ORDERS):
        read = pair(v[2 * i:2 * i + 2], s[2 * i:2 * i + 2], 100.0 / rated)
        out[f"order_{d}"] = {"peak_percent_of_rated_holding_torque": read["magnitude"],
                             "sigma_percent": read["sigma"], "phase_rad": read["phase_rad"]}
    return out


TERMS = EffectTerms(
    effect=Effect.DETENT_TORQUE,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Nothing kept: every hybrid stepper cogs a little, but cogging the recording "
        "resolves is ripple no trim removes, so it is named with its size for QA to judge."),
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("detent",)}, cogging=cogging,
                cogging_slope=cogging_slope, bases=bases),
)
