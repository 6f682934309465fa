"""How a fitted block reads: a value with its σ, a logarithm as its value, a coefficient
pair as magnitude, σ and phase. The effects' readouts are made of these."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit


def sigmas(cov: NDArray[np.float64]) -> NDArray[np.float64]:
    """Each parameter's 1σ from the covariance (a negative rounding on the diagonal is 0)."""
    return np.sqrt(np.maximum(np.diag(cov), 0.0))


def pair(values: NDArray[np.float64], sigma: NDArray[np.float64], scale: float
         ) -> dict[str, float]:
    """A (sin, cos) or (re, im) coefficient pair as magnitude ± σ and phase."""
    mag = math.hypot(values[0], values[1])
    err = math.hypot(sigma[0], sigma[1]) / math.sqrt(2.0)
    return {"magnitude": mag * scale, "sigma": err * scale,
            "phase_rad": math.atan2(values[1], values[0])}


def value(fit: Fit, sig: NDArray[np.float64], name: str, scale: float = 1.0
          ) -> tuple[float, float]:
    """A one-parameter block's value and σ, times ``scale``."""
    sl = fit.model.layout.slices[name]
    return float(fit.params[sl][0]) * scale, float(sig[sl][0]) * scale


def log_value(fit: Fit, sig: NDArray[np.float64], name: str) -> tuple[float, float]:
    """A block fitted as a logarithm, read as its value with the σ it carries."""
    fitted, err = value(fit, sig, name)
    return math.exp(fitted), math.exp(fitted) * err


def harmonic_pairs(fit: Fit, sig: NDArray[np.float64], name: str, orders: tuple[int, ...],
                   *, scale: float, key: str, conjugate: bool = False) -> dict[str, object]:
    """A block of per-order, per-phase coefficient pairs (phase a then b for each order),
    each read as ``{key, sigma_percent, phase_rad}``; ``conjugate``: the pair's second
    coefficient counts the other way."""
    sl = fit.model.layout.slices[name]
    v, s = fit.params[sl], sig[sl]
    out: dict[str, object] = {}
    for i, order in enumerate(orders):
        for p, phase in enumerate(("a", "b")):
            k = 4 * i + 2 * p
            coefficients = np.array([v[k], -v[k + 1]]) if conjugate else v[k:k + 2]
            read = pair(coefficients, s[k:k + 2], scale)
            out[f"order_{order}_phase_{phase}"] = {
                key: read["magnitude"], "sigma_percent": read["sigma"],
                "phase_rad": read["phase_rad"]}
    return out
