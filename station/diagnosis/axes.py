"""The sensor's other two axes: is the element aligned with the load?

An element aligned with the fixture reads the load's ripple on its tangential
axis only. Its radial axis reads the centripetal acceleration, whose ripple is
2Ω·w (Ω the load's mean speed, w its speed ripple): 2Ω/(kω) of the tangential
ripple at order k, a few per cent at most and 90° from it. Its axial axis reads
none. A share of the tangential ripple *in phase* on either axis means the
element is turned on its mount, or its axes couple. No id of the vocabulary
describes that, and the tangential axis alone cannot show it: a turn by α
scales that axis by cos α, which every model's gain absorbs. So it is checked
here, on data the harmonic fit never uses, and reported as a finding.

A turn that shows is then undone on the recording itself (``turned_back``): the
two axes of the plane it turned in are rotated back sample by sample, which is
exact for a rigid turn, where a model of the radial part on the tangential axis
is a first-order approximation built from noisy phasors (development trial
sensor_tilt@1260586362, a disk turned by 17°: the model left a held-out χ² of 2032
where the clean twin has 1170, and friction was named for the difference; turned
back, 1222 and no id).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.analysis.timeline import Timeline
from station.core import SATURATED_COUNTS, Axis
from station.diagnosis.observations import ConditionKey, Observations, OtherAxis, radial_ripple

if TYPE_CHECKING:
    from station.diagnosis.model import Model

COUPLING_TOLERANCE = 0.03
"""In-phase share of the tangential ripple an aligned sensor may show on another axis:
a MEMS element's cross-axis sensitivity (1-2 % in data sheets) plus a degree of
mounting. Above it, and clear of the noise, the element is turned or its axes couple."""

COUPLING_SIGMAS = 5.0
"""Standard errors the share must stand clear of zero (errors inflated by the fit's own
χ²/dof when the axis carries more than coupling and noise)."""


@dataclass(frozen=True)
class AxisCell:
    """One condition and order where the coupled ripple stands out of the axis's noise."""

    condition: int
    order: int
    chi2: float  # of the axis's phasors once the kinematic part is taken out
    dof: int
    axis_rms_mps2: float
    tangential_rms_mps2: float


@dataclass(frozen=True)
class AxisCoupling:
    """What one non-tangential axis carries of the tangential ripple."""

    axis: Axis
    coupling: float  # in-phase share of the tangential ripple
    sigma: float
    kinematic: float  # fitted scale of the centripetal term: ±1 radial, 0 axial
    chi2_per_dof: float  # of the fit (coupling + kinematics) against the axis's noise
    values: int
    cells: tuple[AxisCell, ...] = ()

    @property
    def significant(self) -> bool:
        return (abs(self.coupling) > COUPLING_TOLERANCE
                and abs(self.coupling) > COUPLING_SIGMAS * self.sigma)

    @property
    def turn_rad(self) -> float:
        """The turn of the element that would give this share, were it a turn: the axis
        reads cos α·a_r − sin α·a_t and the tangential one cos α·a_t + sin α·a_r, so the
        share of the second in the first is −tan α (whichever way either axis points)."""
        return math.atan(-self.coupling)

    @property
    def turn_deg(self) -> float:
        return math.degrees(self.turn_rad)

    def measured(self) -> str:
        """What the axis shows, in words: the first part of every finding about it."""
        return (
            f"the sensor's {self.axis.value} axis carries {100 * self.coupling:+.1f} % (± "
            f"{100 * self.sigma:.2g}) of the tangential ripple in phase, where an element "
            f"aligned with the load carries none (tolerance {100 * COUPLING_TOLERANCE:.0f} %)"
        )

    def finding(self) -> str:
        low = 100.0 * (1.0 - math.cos(math.radians(self.turn_deg)))
        return (
            f"{self.measured()}: "
            f"the sensing element is turned by about {abs(self.turn_deg):.0f}° on its mount, "
            "or its axes couple. No id of the vocabulary describes this. The tangential axis "
            f"then reads the ripple about {low:.1f} % low: fitted torques scale with it, "
            "trims (a null is a null) do not"
        )

    def as_dict(self) -> dict[str, Any]:
        return {
            "axis": self.axis.value,
            "in_phase_share": round(self.coupling, 5),
            "in_phase_share_sigma": round(self.sigma, 5),
            "kinematic_scale": round(self.kinematic, 3),
            "chi2_per_dof": round(self.chi2_per_dof, 3),
            "values": self.values,
            "significant": self.significant,
        }


def axis_couplings(obs: Observations) -> tuple[AxisCoupling, ...]:
    """The in-phase share of the tangential ripple on each other axis, with its error."""
    return tuple(_coupling(obs, other) for other in obs.other_axes)


@dataclass(frozen=True)
class ElementTurn:
    """A turn of the sensing element, as measured on the recording and then undone.

    ``conditions`` are those of the observations the coupling was measured on: its
    cells are numbered in them, not in those of the recording turned back.
    """

    coupling: AxisCoupling
    conditions: tuple[ConditionKey, ...]

    @property
    def angle_rad(self) -> float:
        return self.coupling.turn_rad

    def finding(self) -> str:
        c = self.coupling
        return (
            f"{c.measured()}: the sensing element is turned by about "
            f"{abs(c.turn_deg):.1f}° on its mount. "
            "No id of the vocabulary describes this. The diagnosis turned the tangential and "
            f"{c.axis.value} axes back by that angle, sample by sample, before any fit, so "
            "fitted torques are the load's; remount the sensor square to its fixture"
        )


def element_turn(obs: Observations) -> ElementTurn | None:
    """The strongest significant coupling, read as a turn of the element; None if none.

    A turn is the common cause (a sensor glued or screwed on slightly askew); an element
    whose axes couple without turning shows a few per cent at most, inside
    ``COUPLING_TOLERANCE``. Only the strongest is taken: a second turn, about another
    axis, is left to the models (``with_axes_checked``) once this one is undone.
    """
    coupled = [c for c in axis_couplings(obs) if c.significant]
    if not coupled:
        return None
    return ElementTurn(max(coupled, key=lambda c: abs(c.coupling)), obs.conditions)


def turned_back(timeline: Timeline, turn: ElementTurn) -> Timeline:
    """The recording as an element square to its fixture would have read it.

    A turn by α in the plane of the tangential axis T and the other axis Q reads
    T' = cos α·T + sin α·Q and Q' = cos α·Q − sin α·T; the inverse rotation gives both
    back exactly. Counts are rounded again (a quantisation step far below the noise);
    a sample clipped on either axis stays marked as clipped, whatever it rotates to.
    """
    meta = timeline.metadata
    t_col, q_col = meta.tangential_axis.column, turn.coupling.axis.column
    c, s = math.cos(turn.angle_rad), math.sin(turn.angle_rad)
    counts = timeline.accel_counts.astype(np.float64)
    tangential = c * counts[:, t_col] - s * counts[:, q_col]
    other = s * counts[:, t_col] + c * counts[:, q_col]
    out = timeline.accel_counts.copy()
    out[:, t_col] = np.clip(np.rint(tangential), -SATURATED_COUNTS, SATURATED_COUNTS)
    out[:, q_col] = np.clip(np.rint(other), -SATURATED_COUNTS, SATURATED_COUNTS)
    return replace(timeline, accel_counts=out)


def with_axes_checked(obs: Observations) -> Observations:
    """``obs`` marked so that every model carries the radial ripple the tangential axis
    reads, when another axis shows the element turned (its tangential reading is then
    cos α·a_t + sin α·a_r, and the second part, 90° from the first and falling with
    order, was once taken for current distortion)."""
    mixed = any(c.significant for c in axis_couplings(obs))
    return replace(obs, axis_mixed=mixed) if mixed != obs.axis_mixed else obs


def _coupling(obs: Observations, other: OtherAxis) -> AxisCoupling:
    y = obs.phasors
    kin = radial_ripple(obs)[:, :obs.orders]  # centripetal, per unit of the radial sign
    # σ is the spread of the complex phasor; each of its two parts carries half.
    w = np.where(np.isfinite(other.sigma), math.sqrt(2.0) / np.maximum(other.sigma, 1e-12), 0.0)
    # Real parameters (kinematic scale, in-phase share) against complex data: stack the
    # real and imaginary parts of every weighted phasor.
    design = np.stack([np.concatenate([(kin * w).real.ravel(), (kin * w).imag.ravel()]),
                       np.concatenate([(y * w).real.ravel(), (y * w).imag.ravel()])], axis=1)
    data = other.phasors * w
    rhs = np.concatenate([data.real.ravel(), data.imag.ravel()])
    used = np.concatenate([w.ravel(), w.ravel()]) > 0
    values = int(np.count_nonzero(used))
    if values <= 2:
        return AxisCoupling(other.axis, 0.0, math.inf, 0.0, math.nan, values)
    coef, *_ = np.linalg.lstsq(design[used], rhs[used], rcond=None)
    residual = rhs[used] - design[used] @ coef
    chi2_dof = float(residual @ residual) / (values - 2)
    cov = np.linalg.pinv(design[used].T @ design[used]) * max(1.0, chi2_dof)
    kinematic, share = float(coef[0]), float(coef[1])
    coupling = AxisCoupling(other.axis, share, math.sqrt(max(float(cov[1, 1]), 0.0)),
                            kinematic, chi2_dof, values)
    if not coupling.significant:
        return coupling
    return AxisCoupling(coupling.axis, share, coupling.sigma, kinematic, chi2_dof, values,
                        _cells(obs, other, other.phasors - kinematic * kin, w))


def _cells(obs: Observations, other: OtherAxis, left: NDArray[np.complex128],
           w: NDArray[np.float64]) -> tuple[AxisCell, ...]:
    """Per condition and order: χ² of what the axis carries beyond the kinematics."""
    cells = []
    for c in range(len(obs.conditions)):
        rows = (obs.condition == c)[:, None] & (w > 0)
        for k in range(obs.orders):
            here = rows[:, k]
            if not here.any():
                continue
            chi2 = float(np.sum(np.abs(left[here, k] * w[here, k]) ** 2))
            cells.append(AxisCell(
                c, k + 1, chi2, int(2 * np.count_nonzero(here)),
                float(np.sqrt(np.mean(np.abs(other.phasors[here, k]) ** 2))),
                float(np.sqrt(np.mean(np.abs(obs.phasors[here, k]) ** 2)))))
    return tuple(cells)


def measured(model: Model, p: NDArray[np.float64]) -> tuple[NDArray[np.complex128],
                                                    NDArray[np.complex128] | None]:
    """The tangential harmonics as the fixture made them, orders 1..K and beyond:
    the recording's own, with the sensor's bend undone when the model has one."""
    below, above = model.obs.phasors, model.beyond
    k = model.obs.orders
    if model.radial is not None:
        # A turned element reads cos α·a_t + sin α·a_r: the radial part taken out, and
        # the cos α with it (the radius is known, so the swing fixes the scale).
        mix = model.scalar(p, "axis_mix")
        turn = math.sqrt(max(1.0 - mix * mix, 1e-6))
        below = (below - mix * model.radial[:, :k]) / turn
        if above is not None:
            above = (above - mix * model.radial[:, k:]) / turn
    if model.bend is not None:
        c2, c3 = model.block(p, "sensor_bend")
        undo = c2 * model.bend[0] + c3 * model.bend[1]
        below = below - undo[:, :k]
        if above is not None:
            above = above - undo[:, k:]
    return below, above
