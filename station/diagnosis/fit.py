"""Fitting a model to observations, and judging it on conditions held out of the fit.

The solver is scipy's bounded least squares with a Jacobian assembled from
the model's structure: the linear parameters' columns come straight from the
model's design, the per-condition load angles share one finite difference
(each touches only its own condition's rows), and only the few remaining
nonlinear parameters are differenced one by one. A fit of the full model then
costs tens of milliseconds per iteration instead of a second.

Held-out residuals use the standard one-step approximation of leave-one-out
refits: from the full fit, one Gauss-Newton step on the data without the
condition, then the held-out condition's own load angle (a nuisance no other
condition can inform) refitted on its data alone. At these signal-to-noise
ratios the step lands where a full refit would (the tests compare both).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.optimize import least_squares

from station.diagnosis.model import Model

_MAX_NFEV = 60
_STEP = 1e-6


@dataclass(frozen=True)
class Fit:
    """A model at its best parameters, with what judging it needs."""

    model: Model
    params: NDArray[np.float64]
    residuals: NDArray[np.float64]  # weighted, unit variance per part
    jacobian: NDArray[np.float64]

    @property
    def chi2(self) -> float:
        return float(self.residuals @ self.residuals)

    @property
    def parameters(self) -> int:
        return self.model.layout.size

    @property
    def observations(self) -> int:
        return int(self.residuals.size)

    @property
    def bic(self) -> float:
        """Schwarz's criterion with known noise: χ² plus ln(n) per parameter."""
        return self.chi2 + self.parameters * math.log(self.observations)

    def value(self, name: str) -> NDArray[np.float64]:
        return self.params[self.model.layout.slices[name]]


def jacobian(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """d residuals / d parameters, from the model's structure (see the module note)."""
    base = model.residuals(p)
    out = np.empty((base.size, p.size))
    lin = model.linear_index()
    if lin.size:
        _, design = model.linear_design(p)
        flat = design.reshape(design.shape[0], -1)
        out[:, lin] = np.concatenate([flat.real, flat.imag], axis=1).T
    sl = model.layout.slices
    rho = sl["load_angle_rad"]
    shifted = p.copy()
    shifted[rho] += _STEP
    column = (model.residuals(shifted) - base) / _STEP
    rows = model.residual_rows()
    cond = model.obs.condition[rows]
    out[:, rho] = 0.0
    out[np.arange(base.size), rho.start + cond] = column
    done = set(lin.tolist()) | set(range(rho.start, rho.stop))
    for i in range(p.size):
        if i in done:
            continue
        step = _STEP * max(1.0, abs(p[i]))
        shifted = p.copy()
        shifted[i] += step
        out[:, i] = (model.residuals(shifted) - base) / step
    return out


def solve_linear(model: Model, p: NDArray[np.float64], passes: int = 2) -> NDArray[np.float64]:
    """The linear parameters that best fit, the others held (a couple of passes settle
    the small cross terms between them)."""
    idx = model.linear_index()
    out = p.copy()
    for _ in range(passes):
        at_zero, design = model.linear_design(out)
        flat = design.reshape(design.shape[0], -1).T
        a = np.vstack([flat.real, flat.imag])
        b = -np.concatenate([at_zero.real.ravel(), at_zero.imag.ravel()])
        out[idx] = np.linalg.lstsq(a, b, rcond=None)[0]
    return out


def fit(model: Model, starts: list[NDArray[np.float64]], *, keep: int = 2) -> Fit:
    """Bounded least squares from the ``keep`` most promising starts; the best result.

    Every start first gets its linear parameters solved, which is cheap and
    ranks the starts well: the solver then runs only from the best few.
    """
    low, high = model.layout.bounds()
    span = np.where(np.isfinite(low) & np.isfinite(high), high - low, 1.0)
    inside_low = np.where(np.isfinite(low), low + 1e-9 * span, -np.inf)
    inside_high = np.where(np.isfinite(high), high - 1e-9 * span, np.inf)
    screened = []
    for start in starts:
        x0 = np.clip(solve_linear(model, np.clip(start, inside_low, inside_high)),
                     inside_low, inside_high)
        r = model.residuals(x0)
        screened.append((float(r @ r), x0))
    screened.sort(key=lambda item: item[0])
    best: Fit | None = None
    for _, x0 in screened[:keep]:
        result = least_squares(
            model.residuals, x0, jac=lambda p: jacobian(model, p), bounds=(low, high),
            x_scale="jac", method="trf", max_nfev=_MAX_NFEV,
        )
        candidate = Fit(model, result.x, result.fun, result.jac)
        if best is None or candidate.chi2 < best.chi2:
            best = candidate
    assert best is not None, "fit needs at least one start"
    return best


def starts_from(model: Model, base: Fit | None, extra: dict[str, list[float]] | None = None
                ) -> list[NDArray[np.float64]]:
    """Starting points: the base fit's values where the blocks match (load angles
    also from zero, since a model short of an effect bends them to hide it), and
    one start per listed value of a block."""
    template = model.layout.start()
    if base is not None:
        for block in base.model.layout.blocks:
            if model.layout.has(block.name):
                template[model.layout.slices[block.name]] = base.value(block.name)
    starts = [template]
    if base is not None:
        zeroed = template.copy()
        zeroed[model.layout.slices["load_angle_rad"]] = 0.0
        starts.append(zeroed)
    for name, values in (extra or {}).items():
        for v in values:
            for s in list(starts[:2]):
                alt = s.copy()
                alt[model.layout.slices[name]] = v
                starts.append(alt)
    return starts


@dataclass(frozen=True)
class HeldOut:
    """Residuals of each condition predicted by a fit that did not see it."""

    chi2: NDArray[np.float64]  # (C,) per condition
    residuals: NDArray[np.float64]  # same layout as Fit.residuals

    @property
    def total(self) -> float:
        return float(self.chi2.sum())


def held_out(result: Fit) -> HeldOut:
    """Leave-one-condition-out residuals by the one-step approximation (module note)."""
    model = result.model
    r = result.residuals
    jac = result.jacobian
    cond = model.obs.condition[model.residual_rows()]
    rho = model.layout.slices["load_angle_rad"]
    conditions = len(model.obs.conditions)
    chi2 = np.zeros(conditions)
    out = np.empty_like(r)
    for c in range(conditions):
        inside = cond == c
        others = [i for i in range(jac.shape[1]) if i != rho.start + c]
        j_out = jac[~inside][:, others]
        step = -np.linalg.lstsq(j_out, r[~inside], rcond=None)[0]
        predicted = r[inside] + jac[inside][:, others] @ step
        local = jac[inside][:, rho.start + c]
        norm = float(local @ local)
        if norm > 0:
            predicted = predicted - local * float(local @ predicted) / norm
        out[inside] = predicted
        chi2[c] = float(predicted @ predicted)
    return HeldOut(chi2, out)
