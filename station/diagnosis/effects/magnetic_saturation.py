"""Magnetic saturation: the torque constant falling as the current grows, so the ripple's
offsets and gains read differently at each recorded current."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import sigmas
from station.diagnosis.hooks import Grid, Hooks, Params, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations


def saturation_shapes(u2: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                        NDArray[np.float64]]:
    """Kt's two falls in u² = (|i|/I_max)², I_max the recording's largest current.

    An even quartic 1 − D·u² + E·u⁴ falls monotonically on [0, 1] exactly when its
    coefficients are a non-negative mix of these two: 2u² − u⁴ (falls early and levels
    off at the largest current) and u⁴ (flat at zero, steepening). Saturation only ever
    takes torque away, so with the weights kept non-negative the group cannot pose as a
    Kt that rises with the current, which is what a reluctance spring looks like.
    """
    return 2.0 * u2 - u2 * u2, u2 * u2


def saturation_slopes(u2: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                        NDArray[np.float64]]:
    """d/d(u²) of ``saturation_shapes``, beside them so that the law is written once."""
    return 2.0 - 2.0 * u2, 2.0 * u2


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # The two non-negative weights of ``saturation_shapes``: every even quartic law that
    # never rises over the recorded currents, and nothing else (see ``Model.kt_factor``).
    return [Block("saturation", 2, 0.0, 0.0, 0.8, BlockKind.LINEAR)]


def _u2(model: Model, i_a: Grid, i_b: Grid) -> Grid:
    out: Grid = (i_a * i_a + i_b * i_b) / model.largest_A**2
    return out


def kt(model: Model, p: Params, i_a: Grid, i_b: Grid) -> Grid:
    w1, w2 = (float(v) for v in model.block(p, "saturation"))
    b1, b2 = saturation_shapes(_u2(model, i_a, i_b))
    out: Grid = 1.0 - w1 * b1 - w2 * b2
    return out


def kt_slope(model: Model, p: Params, m: Motion) -> tuple[Grid, Grid]:
    w1, w2 = model.block(p, "saturation")
    s1, s2 = saturation_slopes((m.i_a**2 + m.i_b**2) / model.largest_A**2)
    # d(Kt)/d(i) = d(Kt)/d(u²) · 2i/I_max²
    g = -2.0 * (w1 * s1 + w2 * s2) / model.largest_A**2
    return g * m.i_a, g * m.i_b


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    b1, b2 = saturation_shapes((m.i_a**2 + m.i_b**2) / model.largest_A**2)
    return [-parts.modulation * b1 * parts.magnet, -parts.modulation * b2 * parts.magnet]


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    model = fit.model
    sl = model.layout.slices["saturation"]
    w = fit.params[sl]
    sig = sigmas(cov)
    weights = cov[sl, sl]

    def drop(current_A: float) -> tuple[float, float]:
        # The fall is linear in the two weights, so its σ is exact through their covariance.
        shapes = np.array(saturation_shapes(np.array((current_A / model.largest_A) ** 2)))
        return float(shapes @ w), math.sqrt(max(float(shapes @ weights @ shapes), 0.0))

    largest, largest_sig = drop(model.largest_A)
    half, half_sig = drop(0.5 * model.largest_A)
    return {"kt_drop_at_largest_current_percent": 100.0 * largest,
            "sigma_percent": 100.0 * largest_sig,
            "largest_current_mA": 1000.0 * model.largest_A,
            "kt_drop_at_half_that_percent": 100.0 * half,
            "kt_drop_at_half_that_sigma_percent": 100.0 * half_sig,
            "law": "Kt(|i|)/Kt(0) = 1 − w1·(2u² − u⁴) − w2·u⁴, u = |i|/I_max, w1, w2 ≥ 0",
            "w1": float(w[0]), "w1_sigma": float(sig[sl][0]),
            "w2": float(w[1]), "w2_sigma": float(sig[sl][1])}


TERMS = EffectTerms(
    effect=Effect.MAGNETIC_SATURATION,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Nothing kept: every motor saturates somewhat near rated current, but named only "
        "when Kt's fall over the recorded currents is resolved."),
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("saturation",)}, kt=kt, kt_slope=kt_slope,
                bases=bases),
)
