"""Reluctance torque: the phases' own inductance varying with the rotor's angle, a torque
at twice the electrical frequency that grows with the current's square (a magnetic
spring). The paper's form has both phases vary alike; a motor whose phases differ adds a
torque at twice the rotor's electrical angle growing with |i|² (``reluctance_unequal``),
which an independent simulator's detent-plus-reluctance recording carried and which, with
the paper's form alone, went unnamed."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import sigmas, value
from station.diagnosis.hooks import Grid, Hooks, Params, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # Nr·L1/Kt per A: the reluctance torque's peak at 1 A relative to the magnet's; and
    # Nr·L1·u/Kt, the unequal phases' torque −sin 2θe·|i|² in the same units.
    return [Block("reluctance", 1, 0.0, -0.25, 0.25, BlockKind.LINEAR),
            Block("reluctance_unequal", 1, 0.0, -0.25, 0.25, BlockKind.LINEAR)]


def shape(m: Motion) -> Grid:
    """Eq. (3)'s τ_vr per unit of Nr·L1 with (4)-(6): ∂L/∂θ of the winding block."""
    c2, s2 = m.harmonic(2)
    return np.asarray(2.0 * c2 * m.i_a * m.i_b - s2 * (m.i_a * m.i_a - m.i_b * m.i_b),
                      dtype=np.float64)


def unequal_shape(m: Motion) -> Grid:
    """The torque of phases whose reluctance varies unequally, per unit of Nr·L1·u:
    −sin 2θe·(i_A² + i_B²), whatever the currents' direction."""
    _, s2 = m.harmonic(2)
    return np.asarray(-s2 * (m.i_a * m.i_a + m.i_b * m.i_b), dtype=np.float64)


def beside(model: Model, p: Params, m: Motion, made: Grid) -> Grid:
    made = made + model.scalar(p, "reluctance") * shape(m)
    out: Grid = made + model.scalar(p, "reluctance_unequal") * unequal_shape(m)
    return out


def beside_slope(model: Model, p: Params, m: Motion, slope: Grid) -> Grid:
    lam = model.scalar(p, "reluctance")
    c2, s2 = m.harmonic(2)
    slope = slope + lam * (-4.0 * s2 * m.i_a * m.i_b - 2.0 * c2 * (m.i_a**2 - m.i_b**2))
    unequal = model.scalar(p, "reluctance_unequal")
    out: Grid = slope - unequal * 2.0 * c2 * (m.i_a**2 + m.i_b**2)
    return out


def beside_currents(model: Model, p: Params, m: Motion, d_ia: Grid, d_ib: Grid
                    ) -> tuple[Grid, Grid]:
    lam = model.scalar(p, "reluctance")
    c2, s2 = m.harmonic(2)
    unequal = model.scalar(p, "reluctance_unequal")
    d_ia = d_ia + lam * (2.0 * c2 * m.i_b - 2.0 * s2 * m.i_a) - unequal * 2.0 * s2 * m.i_a
    d_ib = d_ib + lam * (2.0 * c2 * m.i_a + 2.0 * s2 * m.i_b) - unequal * 2.0 * s2 * m.i_b
    return d_ia, d_ib


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    return [shape(m), unequal_shape(m)]


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    rated = fit.model.rated_A
    sig = sigmas(cov)
    peak, err = value(fit, sig, "reluctance", 100.0 * rated)
    unequal, unequal_err = value(fit, sig, "reluctance_unequal", 100.0 * rated)
    # τ_vr peaks at Nr·L1·I²; in Kt units per A² the coefficient is Nr·L1/Kt.
    return {"peak_percent_of_holding_torque_at_rated": peak, "sigma_percent": err,
            "unequal_phases_peak_percent_of_holding_torque_at_rated": unequal,
            "unequal_phases_sigma_percent": unequal_err,
            "unequal_phases_law": "−peak·sin 2θe·(i_A² + i_B²)/I_rated², θe the rotor's "
                                  "electrical angle"}


TERMS = EffectTerms(
    effect=Effect.RELUCTANCE_TORQUE,
    blocks=blocks,
    readout=readout,
    healthy_part="Nothing kept: named when the torque's growth with I² is resolved.",
    rivals={
        Effect.LOAD_RESONANCE: (
            "tap test or speed sweep with the rotor held: a compliant coupling keeps its "
            "frequency whatever the current, the magnetic spring's frequency moves with it"),
        Effect.MAGNETIC_SATURATION: (
            "characterize at more currents (a third of rated, and above rated if the drive "
            "allows it briefly): saturation's loss of torque grows faster than I², "
            "reluctance's spring grows as I²; or measure the holding torque against current "
            "with a torque wrench"),
    },
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("reluctance", "reluctance_unequal")}, beside=beside,
                beside_slope=beside_slope, beside_currents=beside_currents, bases=bases),
)
