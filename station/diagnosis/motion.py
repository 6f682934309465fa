"""What the model's evaluations are made of and share: the chain's transfer, the motion
carried back to the rotor, the Newton step, and the memos that keep pieces between
evaluations. Plain values, below the model and its Jacobian (``model``, ``jacobian``)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, fields, replace
from typing import Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from station.diagnosis.hooks import Stage

TRIM_LAG_MAX = 0.5
"""Largest shift of a segment's rotor from its condition's load angle (electrical rad):
a mean torque that moves the rotor further is not a small step on its spring."""
TRIM_LAG_SOFTEST = 0.05
"""Below this spring (|mean ∂torque/∂θe| per A of current, i.e. cos ρ near a load angle of
±87°) a segment is given no slip: the step would be its torque over almost nothing."""
COMMON_GAIN_SIGMA = 0.1
"""A drive's current amplitude as calibrated at its factory: within ±10 % (1σ)."""

_T = TypeVar("_T")


@dataclass(frozen=True)
class Stages:
    """One stage of many chains at once (``chain.chains``): each ``Stage`` field as an
    array over the chains, (m, 1, 1), so that it broadcasts over segments and orders."""

    inertia: NDArray[np.float64]
    damping: NDArray[np.float64]
    spring: NDArray[np.float64]
    spring_damping: NDArray[np.float64]
    ratio: NDArray[np.float64]

    @classmethod
    def of(cls, stages: list[Stage]) -> Stages:
        return cls(**{f.name: np.asarray([getattr(st, f.name) for st in stages],
                                          dtype=np.float64)[:, None, None]
                      for f in fields(cls)})


@dataclass(frozen=True)
class Transfer:
    """The chain per segment and order, linear in the load's angular acceleration α and
    the friction torque F acting on the load: rotor angle θ = A·α + B·F, torque the
    rotor must feel T = C·α + D·F."""

    a: NDArray[np.complex128]
    b: NDArray[np.complex128]
    c: NDArray[np.complex128]
    d: NDArray[np.complex128]


Chain = tuple[Transfer, NDArray[np.complex128] | None, NDArray[np.float64]]
"""The chain's transfer at the modelled orders, its θ per α above them, and the mean
torque its damping takes (``chain.chains``)."""


@dataclass(frozen=True)
class Motion:
    """What the error, its linear design and its sensitivity are all built on."""

    alpha: NDArray[np.complex128]  # load angular acceleration per order (S, K)
    sensor: NDArray[np.complex128]  # the sensor's response per order, clock included (S, K)
    transfer: Transfer
    friction: NDArray[np.complex128]  # friction torque on the load per order (S, K)
    friction_slope: NDArray[np.float64]  # dF/dv at each step's points (S, 3, N)
    te: NDArray[np.float64]  # rotor electrical angle on the grid (S, N)
    sin_te: NDArray[np.float64]
    cos_te: NDArray[np.float64]
    i_a: NDArray[np.float64]
    i_b: NDArray[np.float64]
    modulation: NDArray[np.float64]  # once-per-revolution factor per segment (S, 1)
    taken: NDArray[np.float64]  # mean torque the chain takes: drag and friction (S,)
    lag: NDArray[np.float64]  # each segment's slip from its load angle (``trim_lag``), (S,)
    _powers: dict[int, NDArray[np.complex128]] = field(
        default_factory=dict)

    def shifted(self, delta: NDArray[np.float64] | float) -> Motion:
        """The same motion with each segment's rotor moved by ``delta`` (electrical rad):
        its sines rotated, not evaluated again."""
        turn = np.broadcast_to(np.asarray(delta, dtype=np.float64), self.lag.shape)
        turn_c, turn_s = np.cos(turn)[:, None], np.sin(turn)[:, None]
        return replace(self, te=self.te + turn[:, None],
                       sin_te=self.sin_te * turn_c + self.cos_te * turn_s,
                       cos_te=self.cos_te * turn_c - self.sin_te * turn_s,
                       lag=self.lag + turn, _powers={})

    def harmonic(self, j: int, shift: int = 0) -> tuple[NDArray[np.float64],
                                                       NDArray[np.float64]]:
        """cos and sin of j·(θe − shift·π/2) on the grid, by powers of e^{jθe}: every
        term group needs several multiples of the rotor's angle, and trigonometry of
        each would cost more than the rest of an evaluation."""
        powers = self._powers
        if j not in powers:
            if not powers:
                powers[1] = self.cos_te + 1j * self.sin_te
            z = powers[1]
            # On from the highest power already made: the same products in the same
            # order as from z itself, so the same numbers, with fewer of them.
            lower = max(i for i in powers if i < j)
            power = powers[lower]
            for _ in range(j - lower):
                power = power * z
            powers[j] = power
        c, s = powers[j].real, powers[j].imag
        turn = (j * shift) % 4  # e^{-i·turn·π/2}
        if turn == 0:
            return c, s
        if turn == 1:
            return s, -c
        if turn == 2:
            return -c, -s
        return -s, c


@dataclass(frozen=True)
class Inputs:
    """What a motion is made from at one parameter point, (S, …) each: every piece that a
    nonlinear parameter enters (``jacobian.motion_columns``)."""

    sensor: NDArray[np.complex128]
    alpha: NDArray[np.complex128]
    transfer: Transfer
    swing_above: NDArray[np.complex128] | None  # rotor angle at the orders above K
    friction: NDArray[np.complex128]
    friction_slope: NDArray[np.float64]
    taken: NDArray[np.float64]
    rho: NDArray[np.float64]  # each segment's load angle
    i_a: NDArray[np.float64]
    i_b: NDArray[np.float64]
    modulation: NDArray[np.float64]
    unbalance: NDArray[np.float64]  # the once-per-revolution load per segment (S,)


@dataclass(frozen=True)
class Linearised:
    """What every analytic Jacobian column at one point shares (``jacobian.linear_jacobian``,
    ``jacobian.motion_columns``): the motion before and after its slip, the magnetic spring
    on the grid at both with its bend along the angle, and the load acceleration the
    step asks for, as the rotor's swing on the grid."""

    motion: Motion
    first: Motion  # before the slip (``trim_lag``)
    slope: NDArray[np.float64]  # ∂torque/∂θe on the grid, (S, N)
    bend: NDArray[np.float64]  # ∂²torque/∂θe², (S, N)
    slope1: NDArray[np.float64]  # both before the slip
    bend1: NDArray[np.float64]
    acts: NDArray[np.bool_]  # segments whose slip moves (soft springs and caps do not)
    step: Step
    alpha: NDArray[np.complex128]  # the step's load acceleration, (S, K)
    swing: NDArray[np.float64]  # its rotor angle on the grid (mech. rad), (S, N)

    @property
    def spring1(self) -> NDArray[np.float64]:
        out: NDArray[np.float64] = self.slope1.mean(axis=1)
        return out


@dataclass(frozen=True)
class Step:
    """The Newton step that carries a segment's equation error (torque, Kt units) into
    the error of its measured harmonics (weighted sensor units): the inverse of the
    equation error's derivative in the measured motion, and the sensor's own factor.

    The derivative is a matrix, not one number per order: the spring's stiffness varies
    over the electrical period (amplifier offsets and gain errors, the swing itself),
    so the rotor's swing at one order makes torque at its neighbours. Divided by the
    period's mean stiffness alone, the noise of one order leaked into the next by an
    amount the parameters set, and a fit could shrink its χ² by reshaping the spring
    instead of describing the motion: on a clean development belt with offsets of a
    fifth of its current (none@204) a negative reluctance or a steep saturation gained
    40 to 100 in χ², in every noise draw, and more the more noise there was. With the
    whole derivative, each residual's noise is the measurement's own, whatever the
    parameters, and both gained nothing; a true reluctance (reluctance_torque@1517242068)
    was then fitted at its value (0.032 against 0.031) instead of at half of it.
    """

    inverse: NDArray[np.float64]  # (S, 2K, 2K): on [Re; Im] of an error, per segment
    factor: NDArray[np.complex128]  # (S, K): radius · sensor response · weight

    def alpha(self, error: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """The step in the load's acceleration, (…, S, K), for errors (…, S, K)."""
        k = error.shape[-1]
        stacked = np.concatenate([error.real, error.imag], axis=-1)
        if stacked.ndim == 2:
            moved = (self.inverse @ stacked[..., None])[..., 0]
        else:  # many errors: one product per segment, the errors side by side
            shape = stacked.shape
            side = np.moveaxis(stacked.reshape(-1, *shape[-2:]), 0, -1)
            moved = np.moveaxis(self.inverse @ side, -1, 0).reshape(shape)
        out: NDArray[np.complex128] = moved[..., :k] + 1j * moved[..., k:]
        return out

    def apply(self, error: NDArray[np.complex128]) -> NDArray[np.complex128]:
        """The weighted harmonic residuals, (…, S, K), of equation errors (…, S, K)."""
        out: NDArray[np.complex128] = self.alpha(error) * self.factor
        return out


class Memo(Generic[_T]):
    """The last few values of a piece of the model that reads only a few parameters.

    A finite-difference Jacobian moves one parameter at a time, so every column finds
    all but the pieces that parameter enters as the base point left them: the sensor's
    response with a drifting clock, the currents, the chain's transfer are then made
    once per Jacobian instead of once per column. A parameter that enters a kept piece
    must be among its keys (the ``*_KEYS`` above), or the piece goes stale: a test
    compares a model with every group against one made afresh for each evaluation.

    The value asked for again last is kept first: the point a Jacobian is taken at,
    whose pieces every column that does not move them asks for. A value made afresh (a
    column that moves the piece's parameters) goes in behind it, so that a run of such
    columns pushes out only each other. Kept as the two made last, the base's value was
    gone after two such columns in a row (the sensor's filter, a friction's levels) and
    made again for the next column: on development friction@5700 a third of the
    sensor's and the friction's pieces were made again so.
    """

    def __init__(self, index: NDArray[np.intp]) -> None:
        self.index = index
        self.entries: list[tuple[bytes, _T]] = []

    def get(self, p: NDArray[np.float64], compute: Callable[[], _T]) -> _T:
        key = p[self.index].tobytes()
        for i, (known, value) in enumerate(self.entries):
            if known == key:
                if i:
                    self.entries.insert(0, self.entries.pop(i))
                return value
        value = compute()
        self.entries.insert(1 if self.entries else 0, (key, value))
        del self.entries[MEMO_ENTRIES:]
        return value


MEMO_ENTRIES = 3
"""Values each ``Memo`` keeps: the one asked for again last, and the two made last (two
points evaluated in turn, as a trust region tries its steps, are then both kept)."""


def real_map(p_mat: NDArray[np.complex128], q_mat: NDArray[np.complex128]
              ) -> NDArray[np.float64]:
    """y = P·x + Q·conj x as one real matrix on [Re; Im], (S, 2K, 2K)."""
    k = p_mat.shape[-1]
    plus, minus = p_mat + q_mat, p_mat - q_mat
    out = np.empty((*p_mat.shape[:-2], 2 * k, 2 * k))
    out[..., :k, :k] = plus.real
    out[..., :k, k:] = -minus.imag
    out[..., k:, :k] = plus.imag
    out[..., k:, k:] = minus.real
    return out


def stacked(columns: NDArray[np.complex128]) -> NDArray[np.float64]:
    """A map's responses to the 2K unit changes (2K, S, K) as its real matrix (S, 2K, 2K)."""
    out: NDArray[np.float64] = np.concatenate([columns.real, columns.imag], axis=-1
                                              ).transpose(1, 2, 0)
    return out


def flatten(harmonic: NDArray[np.complex128], dc: NDArray[np.float64],
            prior: NDArray[np.float64]) -> NDArray[np.float64]:
    """Residuals as a solver takes them: the harmonics' real parts, their imaginary parts,
    each segment's torque balance, the prior."""
    return np.concatenate([harmonic.real.ravel(), harmonic.imag.ravel(), dc, prior])
