"""The torque model of the paper, its mechanical chain, its sensor, and the effects beyond.

The model is fitted as an *equation error* on the motion the sensor measured.
Each segment's harmonics 1..K give the load's periodic motion; the sensor's
own response is undone; the chain of inertias and springs (a rigid disk, or
the belt the fixture declares) maps the load's motion back to the rotor's
motion and to the torque the rotor must have felt; the torque model,
evaluated on that same rotor motion with the currents the drive made, says
what torque the motor did make. The two must agree at every order.
Evaluating the torque on the measured motion, instead of integrating the
equations of motion, keeps the rotor's large-swing nonlinearity (a few tenths
of an electrical radian at untrimmed offsets, which puts strong 3rd to 5th
harmonics into any recording) inside the model at no cost, and the same holds
for friction, which is evaluated on the load's measured velocity.

The disagreement is carried back to the measurement by a Newton step: the
inverse of its derivative in the measured acceleration (the linearised chain
and the spring, whose stiffness varies over the period and so couples each
order to its neighbours: ``Step``), times the sensor's response. Residuals
are then in m/s² like the measurement itself, each carrying the measurement's
own noise whatever the parameters, and weighting them by its uncertainty
makes the fit close to the output-error maximum-likelihood one.

All torques are in units of the torque constant Kt (so in A): Kt itself and
the inertias cannot both be known from an acceleration alone, only their
ratios, and the parameters are chosen to be the identifiable ones (natural
frequencies, damping ratios, relative harmonic amplitudes). Scale parameters
(frequencies, ratios) are fitted as logarithms: they span decades, and a
relative step is what the data resolve.

Sign conventions follow ``station.physics.motor`` and ICD.md §2: phase A
carries cos x, phase B sin x, the rotor's electrical angle is x − ρ plus its
oscillation, and a phasor Z of order k means Re(Z·e^{jkx}).

Physics beyond the paper's model enters as *term groups*, one per id of
CLI.md's vocabulary (``GROUPS``); each adds a few parameters to this one
model, so any combination of them is a model too.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, fields, replace
from typing import Any, Generic, TypeVar

import numpy as np
from numpy.typing import NDArray

from station.core import GAIN_UNITY, Effect
from station.diagnosis import effects
from station.diagnosis.effects.current_distortion import DISTORTION_ORDERS, dead_time_knee_A
from station.diagnosis.effects.detent_torque import DETENT_ORDERS
from station.diagnosis.effects.flux_harmonics import FLUX_ORDERS
from station.diagnosis.effects.friction import FLOOR_SMOOTHING, FRICTION_TURN_SHARE
from station.diagnosis.effects.magnetic_saturation import saturation_shapes, saturation_slopes
from station.diagnosis.layout import Block, BlockKind, ChainKind, Layout, ModelSpec
from station.diagnosis.observations import MODEL_FLOOR, Observations

GRID = 48
"""Points per electrical period where torques are evaluated: orders up to 23 alias-free,
and an order must reach 40 to fold onto the 8 analysed. The swing's orders reach 16, so
products of a few of them fit; measured on seven recordings' fitted models (cogging
several times the magnet torque among them), every residual moved by under 1e-5 σ
from a 64-point grid, for a quarter less of every evaluation's grid work."""

TRIM_LAG_MAX = 0.5
"""Largest shift of a segment's rotor from its condition's load angle (electrical rad):
a mean torque that moves the rotor further is not a small step on its spring."""
ANGLE_STEP = 1e-6
"""Electrical rad: the step along the rotor angle that differences a smooth torque basis
into its slope (``Model.linear_jacobian``)."""
NEAR_REFINE = 4
NEAR_START = 1e-3
NEAR_DONE = 1e-14
"""Newton–Schulz passes at most, the error of the start beyond which the matrix is
inverted afresh instead, and the error at which refining stops (``Model.step``):
a difference step leaves an error near 1e-6, gone to rounding after two passes."""
DEAD_TIME_OVERSAMPLE = 4
"""How much finer than the grid a dead time's turns are formed before they are cut to the
grid's orders (``Model.dead_time_turns``)."""
TRIM_LAG_SOFTEST = 0.05
"""Below this spring (|mean ∂torque/∂θe| per A of current, i.e. cos ρ near a load angle of
±87°) a segment is given no slip: the step would be its torque over almost nothing."""

QUARTER = math.pi / 2.0

COMMON_GAIN_SIGMA = 0.1
"""A drive's current amplitude as calibrated at its factory: within ±10 % (1σ)."""

SENSOR_MIN_BANDWIDTH = 0.4
"""Of the SYNC rate: what ICD.md §3 promises of the sensor's own bandwidth."""
SENSOR_MAX_DAMPING = 1.5
"""Of the sensor's low-pass (a first-order one is a heavily damped second-order one)."""


def layout_for(spec: ModelSpec, obs: Observations) -> Layout:
    """Parameter blocks of a model; effect blocks start where the effect is absent."""
    lay = Layout()
    t_ms = obs.metadata.sync_period_s * 1e3
    # The sensor's own low-pass 1/(1 + a1·s + a2·s²): a1 its delay at low frequency, a2 its
    # curvature. Both ≥ 0 (a causal, stable filter), and no slower than ICD.md lets it be:
    # a sample is taken at its SYNC, through a bandwidth of at least 40 % of the SYNC rate.
    w_min = 2.0 * math.pi * SENSOR_MIN_BANDWIDTH / obs.metadata.sync_period_s * 1e-3  # rad/ms
    lay.add(Block("sensor_a1_ms", 1, 0.45 * t_ms, 0.0, 2.0 * SENSOR_MAX_DAMPING / w_min))
    lay.add(Block("sensor_a2_ms2", 1, 0.1 * t_ms * t_ms, 0.0, 1.0 / w_min**2))
    lay.add(Block("load_angle_rad", len(obs.conditions), 0.0, -1.45, 1.45, BlockKind.ANGLES))
    # Linear blocks have physical bounds too: without them a drive making no current at
    # all (gain error −100 %) and a floating rotor "explain" any motion.
    lay.add(Block("amp_offset_mA", 2, 0.0, -2000.0, 2000.0, BlockKind.LINEAR))
    lay.add(Block("amp_gain_error", 2, 0.0, -0.45, 0.45, BlockKind.LINEAR))
    lay.add(Block("log_rotor_hz", 1, math.log(120.0), math.log(3.0), math.log(8000.0)))
    lay.add(Block("rotor_damping_ratio", 1, 0.05, 0.0, 4.0))
    if spec.chain is ChainKind.BELT:
        lay.add(Block("log_load_ratio", 1, math.log(3.0), math.log(1e-3), math.log(1e4)))
        lay.add(Block("log_belt_hz", 1, math.log(60.0), math.log(1.0), math.log(8000.0)))
        lay.add(Block("belt_damping_ratio", 1, 0.05, 0.0, 3.0))
        # The load's own bearings and seals: viscous drag on the load, as a damping ratio
        # of the load on its belt (a disk's is part of the rotor's damping).
        lay.add(Block("load_damping_ratio", 1, 0.05, 0.0, 10.0))
    # What a healthy unit always has (its bearings' friction), then each id's own blocks.
    for block in effects.nominal_blocks(spec, obs):
        lay.add(block)
    for effect in sorted(spec.effects):
        for block in effects.terms(effect).blocks(spec, obs):
            lay.add(block)
    if obs.axis_mixed:
        # The share of the radial ripple the tangential axis reads: sin α for an element
        # turned by α (either sign: the radial axis's direction is not declared).
        lay.add(Block("axis_mix", 1, 0.0, -0.7, 0.7))
    if spec.sensor_bend:
        # c2, c3 as fractions of the full scale: the worst deviation of a MEMS element's
        # transfer is a few per cent; a third of the range is no longer a sensor.
        lay.add(Block("sensor_bend", 2, 0.0, -BEND_LIMIT, BEND_LIMIT))
    return lay


BEND_LIMIT = 0.3
"""Largest |c2|, |c3| of a sensor transfer the model allows (fractions of full scale)."""

BEND_GRID = 128
"""Points per electrical period where the bend's products are formed: the cube of order
16 reaches order 48, which a grid of 128 resolves without folding."""


def clock_middle(obs: Observations) -> float:
    """The sample number (from the first SYNC) the clock's phase is counted from."""
    return 0.5 * (float(obs.span[0, 0]) + float(obs.span[-1, 1]))


def radial_ripple(obs: Observations) -> NDArray[np.complex128]:
    """The centripetal ripple 2Ω·w at the sensor, orders 1..K then beyond, from the
    measured tangential ripple itself (w = a/(jkω), to first order)."""
    phasors = obs.phasors if obs.beyond is None else np.hstack([obs.phasors, obs.beyond])
    k = np.arange(1, phasors.shape[1] + 1, dtype=np.float64)
    out: NDArray[np.complex128] = (2.0 * obs.load_speed[:, None] * phasors
                                   / (1j * obs.omega[:, None] * k[None, :]))
    return out


def sawtooth_mean(u0: NDArray[np.float64], u1: NDArray[np.float64],
                  a: NDArray[np.float64]) -> NDArray[np.complex128]:
    """Mean of e^{-ja·frac(u)} for u running linearly from ``u0`` to ``u1`` (per row),
    for each column of ``a``: a wrapping clock's delays over a segment are T·frac(u).

    With G(v) = ∫₀ᵛ e^{-jax} dx = (1 − e^{-jav})/(ja), an antiderivative of the
    periodic integrand is F(u) = ⌊u⌋·G(1) + G(frac u), and the mean is
    [F(u₀) − F(u₁)]/(u₀ − u₁): exact, and smooth in the clock's rate and phase.
    """
    small = np.abs(a) < 1e-9
    ja = np.where(small, 1.0, 1j * a)

    def g(v: NDArray[np.float64]) -> NDArray[np.complex128]:
        out: NDArray[np.complex128] = np.where(small, v, (1.0 - np.exp(-ja * v)) / ja)
        return out

    def big_f(u: NDArray[np.float64]) -> NDArray[np.complex128]:
        part = np.broadcast_to((u - np.floor(u))[:, None], a.shape)
        out: NDArray[np.complex128] = np.floor(u)[:, None] * g(np.ones_like(a)) + g(part)
        return out

    width = (u0 - u1)[:, None]
    still = np.abs(width) < 1e-9  # no drift across the segment: the delay is constant
    safe = np.where(still, 1.0, width)
    mean = np.exp(-1j * a * np.mod(0.5 * (u0 + u1), 1.0)[:, None])
    out: NDArray[np.complex128] = np.where(still, mean, (big_f(u0) - big_f(u1)) / safe)
    return out


def bend_bases(obs: Observations) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
    """Harmonics of m²/FS and m³/FS² per segment, m the measured tangential waveform
    (its mean and every demodulated order), orders 1..K then the orders beyond.

    A sensor reading m = a + c2·a²/FS + c3·a³/FS² is undone to first order in c by
    a = m − c2·m²/FS − c3·m³/FS²: the products of the measurement itself, fixed by the
    data, so the bend enters the model linearly.
    """
    phasors = obs.phasors if obs.beyond is None else np.hstack([obs.phasors, obs.beyond])
    k = np.arange(1, phasors.shape[1] + 1, dtype=np.float64)
    x = 2.0 * np.pi * np.arange(BEND_GRID) / BEND_GRID
    synth = np.exp(1j * np.outer(k, x))
    dc = np.zeros(obs.count) if obs.dc is None else obs.dc
    wave = dc[:, None] + (phasors @ synth).real
    full_scale = obs.metadata.sensor_full_scale_mps2
    analyse = 2.0 / BEND_GRID * np.exp(-1j * np.outer(x, k))
    square = (wave**2 / full_scale) @ analyse
    cube = (wave**3 / full_scale**2) @ analyse
    return np.asarray(square, dtype=np.complex128), np.asarray(cube, dtype=np.complex128)




@dataclass(frozen=True)
class _Stage:
    """One inertia of the chain (μ = J/Kt, γ = c/Kt) and the spring to the next one."""

    inertia: float
    damping: float
    spring: float = 0.0  # κ = k/Kt of the spring to the next inertia (0: last inertia)
    spring_damping: float = 0.0
    ratio: float = 1.0  # next angle per this angle through the spring


@dataclass(frozen=True)
class _Stages:
    """One stage of many chains at once (``Model.chains``): each ``_Stage`` field as an
    array over the chains, (m, 1, 1), so that it broadcasts over segments and orders."""

    inertia: NDArray[np.float64]
    damping: NDArray[np.float64]
    spring: NDArray[np.float64]
    spring_damping: NDArray[np.float64]
    ratio: NDArray[np.float64]

    @classmethod
    def of(cls, stages: list[_Stage]) -> _Stages:
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
torque its damping takes (``Model.chains``)."""


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
class _Inputs:
    """What a motion is made from at one parameter point, (S, …) each: every piece that a
    nonlinear parameter enters (``Model.motion_columns``)."""

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
class _Linearised:
    """What every analytic Jacobian column at one point shares (``Model.linear_jacobian``,
    ``Model.motion_columns``): the motion before and after its slip, the magnetic spring
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


SENSOR_KEYS = ("sensor_a1_ms", "sensor_a2_ms2", "clock_drift_ppm", "clock_phase")
"""What the sensor's response is made of (``Model.sensor_response``)."""
MEASURED_KEYS = ("axis_mix", "sensor_bend")
"""What the measured tangential motion is corrected with (``Model.measured``)."""
CURRENT_KEYS = ("amp_offset_mA", "amp_gain_error", "distortion", "dead_time", "current_lag_ms")
"""What the currents the drive made are made of (``Model.current_coefficients``)."""
CHAIN_KEYS = ("log_rotor_hz", "rotor_damping_ratio", "log_load_ratio", "log_belt_hz",
              "belt_damping_ratio", "load_damping_ratio", "coupling_fraction",
              "log_coupling_hz", "coupling_damping_ratio")
"""What the chain's inertias, springs and dampers are made of (``Model.stages``)."""
FRICTION_KEYS = ("friction_coulomb", "log_friction_smoothing")
"""What the load's friction is made of, beside the load's motion (``Model.friction_torque``)."""
TORQUE_KEYS = ("flux", "saturation", "detent", "reluctance", "reluctance_unequal")
"""What the torque reads beside the motion (``Model.torque``, ``Model.torque_slope``)."""

_T = TypeVar("_T")


class _Memo(Generic[_T]):
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
"""Values each ``_Memo`` keeps: the one asked for again last, and the two made last (two
points evaluated in turn, as a trust region tries its steps, are then both kept)."""


_BAND = 3
"""A step's mean depends on its own grid point's velocity and its two neighbours'."""


SETTLED_SCALE = 20.0
"""|v|/ε beyond which the smoothed sign is ±1 to the last bit: tanh rounds to 1 from 19.1,
and what a step's secant adds (about 4·e^{−2|v|/ε}) is below half an ulp of 1 from 18.8."""


def _cell_means(v: NDArray[np.float64], eps: float) -> tuple[NDArray[np.float64], ...]:
    """Means of t = tanh(v/ε) and of t² over each grid step centred on a grid point, v
    straight between neighbouring points (cyclic, last axis), (…, N) each; and how each
    mean moves with the velocity at the previous, its own and the next point, (…, 3, N).

    A row whose velocity keeps one sign at least ``SETTLED_SCALE``·ε from zero over its
    whole period (the load never near stopping: nine rows in ten of a friction fit on
    development friction@5700) is ±1, 1 and no slope, and only the other rows are made:
    the same numbers to the bit, and most of the cost of friction's shapes saved.
    """
    n = v.shape[-1]
    rows = v.reshape(-1, n)
    half = 0.5 * (rows + np.roll(rows, -1, axis=-1))
    bound = SETTLED_SCALE * eps
    low = np.minimum(rows.min(axis=1), half.min(axis=1))
    high = np.maximum(rows.max(axis=1), half.max(axis=1))
    forward, reverse = low > bound, high < -bound
    moving = ~(forward | reverse)
    if moving.all():
        return _cell_means_made(v, eps)
    mean_t = np.zeros_like(rows)
    mean_t[forward], mean_t[reverse] = 1.0, -1.0
    mean_t2 = np.ones_like(rows)
    band_t = np.zeros((rows.shape[0], _BAND, n))
    band_t2 = np.zeros_like(band_t)
    if moving.any():
        mean_t[moving], mean_t2[moving], band_t[moving], band_t2[moving] = _cell_means_made(
            rows[moving], eps)
    lead = v.shape[:-1]
    return (mean_t.reshape(v.shape), mean_t2.reshape(v.shape),
            band_t.reshape(*lead, _BAND, n), band_t2.reshape(*lead, _BAND, n))


def _cell_means_made(v: NDArray[np.float64], eps: float) -> tuple[NDArray[np.float64], ...]:
    """``_cell_means`` made in full on every row.

    Each half step is a secant of an antiderivative (ε·ln cosh(v/ε) for t, v − ε·t for
    t²), so a jump of the sign inside a step moves the mean as far as the crossing
    moved. The differences are formed without subtracting nearly equal values: where the
    sign has settled, what ε changes is a millionth of what the subtraction rounded, and
    a Jacobian's difference in ε was 7e-4 off.
    """
    half = 0.5 * (v + np.roll(v, -1, axis=-1))  # straight from point n to n + 1
    # Each step's ends: the midpoint before (the last one rolled), the point, the midpoint
    # after; what each end needs is made once, for the point and the midpoint after.
    both = np.stack([v, half]) / eps
    size = np.abs(both)
    made = (both, size, np.tanh(both), np.log1p(np.exp(-2.0 * size)))  # ln cosh: |x| + tail − ln 2
    x, ax, tanh, tail = ([np.roll(q[1], 1, axis=-1), q[0], q[1]] for q in made)
    ends = [np.roll(half, 1, axis=-1), v, half]
    means = [np.zeros_like(v), np.zeros_like(v)]
    band = np.zeros((2, *v.shape[:-1], _BAND, v.shape[-1]))
    for first, (i, j) in enumerate(((0, 1), (1, 2))):
        a, b = ends[i], ends[j]
        d = b - a
        # Across a step far narrower than ε the shape is straight: its midpoint stands
        # for the secant.
        flat = np.abs(d) <= 1e-6 * eps
        safe = np.where(flat, 1.0, d)
        # tanh y − tanh x = sinh(y − x)/(cosh x·cosh y), in logarithms (the ln 2 of each
        # ln cosh is the 2 in front).
        span = np.abs(x[j] - x[i])
        dt = (np.sign(d) * 2.0 * -np.expm1(-2.0 * span)
              * np.exp(span - ax[i] - tail[i] - ax[j] - tail[j]))
        # ε·(ln cosh y − ln cosh x)/(b − a): its part |b| − |a| is ±(b − a) itself when
        # both have one sign.
        settled = np.where(a * b > 0, np.sign(a), (np.abs(b) - np.abs(a)) / safe)
        tm = np.tanh(0.5 * (x[i] + x[j])) if flat.any() else np.zeros_like(d)
        dm = (1.0 - tm * tm) / eps
        shapes = (
            (np.where(flat, tm, settled + eps * (tail[j] - tail[i]) / safe),
             tanh[i], tanh[j], dm),
            (np.where(flat, tm * tm, 1.0 - eps * dt / safe),
             tanh[i] ** 2, tanh[j] ** 2, 2.0 * tm * dm),
        )
        for k, (mean, at_a, at_b, slope) in enumerate(shapes):
            means[k] = means[k] + 0.5 * mean
            # A secant's ends move it by (S − f(a))/(b − a) and (f(b) − S)/(b − a).
            by_a = np.where(flat, 0.5 * slope, (mean - at_a) / safe)
            by_b = np.where(flat, 0.5 * slope, (at_b - mean) / safe)
            if first == 0:  # from the midpoint with the previous point to this point
                band[k, ..., 0, :] += 0.25 * by_a
                band[k, ..., 1, :] += 0.25 * by_a + 0.5 * by_b
            else:  # from this point to the midpoint with the next
                band[k, ..., 1, :] += 0.5 * by_a + 0.25 * by_b
                band[k, ..., 2, :] += 0.25 * by_b
    return means[0], means[1], band[0], band[1]


def _real_map(p_mat: NDArray[np.complex128], q_mat: NDArray[np.complex128]
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


def _stacked(columns: NDArray[np.complex128]) -> NDArray[np.float64]:
    """A map's responses to the 2K unit changes (2K, S, K) as its real matrix (S, 2K, 2K)."""
    out: NDArray[np.float64] = np.concatenate([columns.real, columns.imag], axis=-1
                                              ).transpose(1, 2, 0)
    return out


class Model:
    """A model (nominal, or nominal plus term groups) bound to one set of observations."""

    def __init__(self, spec: ModelSpec, obs: Observations) -> None:
        self.spec = spec
        self.obs = obs
        self.layout = layout_for(spec, obs)
        meta = obs.metadata
        self.rotor_teeth = meta.rotor_teeth
        self.radius = meta.sensor_radius_m
        self.gear_ratio = meta.gear_ratio
        self.rated_A = meta.rated_current_mA / 1000.0
        self.largest_A = float(max(np.max(obs.amplitude_A), 1e-3))
        k = np.arange(1, obs.orders + 1, dtype=np.float64)
        self.k = k
        x = 2.0 * np.pi * np.arange(GRID) / GRID
        self.x = x
        self.synth = np.exp(1j * np.outer(k, x))  # (K, N): order k at grid point n
        self.analyse = 2.0 / GRID * np.exp(-1j * np.outer(x, k))  # (N, K)
        self._analyse_parts = np.ascontiguousarray(
            np.concatenate([self.analyse.real, self.analyse.imag], axis=1))  # (N, 2K)
        self._cell_gain = np.sinc(k / GRID)  # a grid step's mean of order k
        # The slope's harmonics 0 … 2K, and the pairs of orders each couples (``step``).
        self.slope_analyse = np.exp(-1j * np.outer(x, np.arange(2 * obs.orders + 1))) / GRID
        orders = np.arange(1, obs.orders + 1)
        # (2, K, K): the slope harmonics k − j and k + j, as indices into −2K … 2K.
        self.order_pairs = np.stack([orders[:, None] - orders[None, :],
                                     orders[:, None] + orders[None, :]]) + 2 * obs.orders
        # (S, K): d/dt of order k, rad/s
        self.jw: NDArray[np.complex128] = np.asarray(1j * obs.omega[:, None] * k[None, :],
                                                     dtype=np.complex128)
        # σ is the spread of the complex phasor; each of its two parts carries half.
        self.weight = math.sqrt(2.0) / np.maximum(obs.sigma, 1e-12)
        self.trim_offset_A = obs.trims[:, :2] * 1e-3
        self.trim_gain = obs.trims[:, 2:] / GAIN_UNITY
        self.amp = obs.amplitude_A[:, None]
        # Current harmonics on the grid: order 1 (the table) and the distortion orders.
        self.current_orders = np.array([1, *DISTORTION_ORDERS], dtype=np.float64)
        self.current_synth = np.exp(1j * np.outer(self.current_orders, x))  # (H, N)
        fine = 2.0 * np.pi * np.arange(DEAD_TIME_OVERSAMPLE * GRID) / (DEAD_TIME_OVERSAMPLE * GRID)
        self._dead_synth = np.exp(1j * np.outer(self.current_orders, fine))
        self._dead_knee = dead_time_knee_A(obs)
        self.load_speed = obs.load_speed[:, None]  # rad/s at the load
        self.bend = bend_bases(obs) if spec.sensor_bend else None
        self.radial = radial_ripple(obs) if obs.axis_mixed else None
        self._clock_n = self._clock_samples()
        self.clock_middle = clock_middle(obs)
        self._last: tuple[NDArray[np.float64], Motion] | None = None
        sensor = (*SENSOR_KEYS, *MEASURED_KEYS)
        self._sensor: _Memo[NDArray[np.complex128]] = self._memo(SENSOR_KEYS)
        self._sensor_beyond: _Memo[NDArray[np.complex128]] = self._memo(SENSOR_KEYS)
        self._alpha: _Memo[tuple[NDArray[np.complex128], NDArray[np.complex128],
                                 NDArray[np.complex128] | None]] = self._memo(sensor)
        self._friction: _Memo[tuple[NDArray[np.complex128], NDArray[np.float64],
                                    NDArray[np.float64]]] = self._memo((*sensor, *FRICTION_KEYS))
        # Friction's shapes do not move with its levels: a Jacobian's columns of the levels
        # would otherwise make them again, most of a friction model's evaluation.
        self._friction_shapes: _Memo[tuple[NDArray[np.float64], ...]] = self._memo(
            (*sensor, "log_friction_smoothing"))
        self._chain: _Memo[Chain] = self._memo(CHAIN_KEYS)
        self._coefficients: _Memo[tuple[NDArray[np.float64], NDArray[np.complex128],
                                        NDArray[np.float64], NDArray[np.complex128]]] = (
            self._memo(CURRENT_KEYS))
        self._currents: _Memo[tuple[NDArray[np.float64], NDArray[np.float64]]] = self._memo(
            CURRENT_KEYS)
        self._residuals: _Memo[NDArray[np.float64]] = _Memo(np.arange(self.layout.size))
        self._linear_memo: _Memo[_Linearised] = _Memo(np.arange(self.layout.size))
        self._torque_index = self._memo(TORQUE_KEYS).index
        # The torque made and the error's step on the motion at p: the residuals and the
        # linear design (both asked for at each Jacobian's point) share them.
        self._made: _Memo[tuple[NDArray[np.float64], Step]] = _Memo(
            np.arange(self.layout.size))
        # The measured orders above K: part of the swing, never of the residual.
        beyond = obs.beyond if obs.beyond is not None and obs.beyond.size else None
        self.beyond = beyond
        if beyond is not None:
            kb = np.arange(obs.orders + 1, obs.orders + 1 + beyond.shape[1], dtype=np.float64)
            self.k_beyond = kb
            self.jw_beyond: NDArray[np.complex128] = np.asarray(
                1j * obs.omega[:, None] * kb[None, :], dtype=np.complex128)
            self.synth_beyond = np.exp(1j * np.outer(kb, x))

    def _memo(self, names: tuple[str, ...]) -> _Memo[_T]:
        """A memo keyed on the named blocks this model has."""
        every = np.arange(self.layout.size)
        parts = [every[self.layout.slices[n]] for n in names if self.layout.has(n)]
        return _Memo(np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp))

    # ------------------------------------------------------------------ pieces
    def with_values(self, p: NDArray[np.float64], values: dict[str, list[float]]
                    ) -> NDArray[np.float64]:
        """A copy of ``p`` with the named blocks set (names this model lacks are ignored)."""
        out = p.copy()
        for name, v in values.items():
            if self.layout.has(name):
                out[self.layout.slices[name]] = v
        return out

    def chain_index(self) -> NDArray[np.intp]:
        """Where the chain's parameters sit (``CHAIN_KEYS``): what ``stages`` reads."""
        return self._chain.index

    def _p(self, p: NDArray[np.float64], name: str) -> NDArray[np.float64]:
        return p[self.layout.slices[name]]

    def _scalar(self, p: NDArray[np.float64], name: str) -> float:
        return float(p[self.layout.slices[name]][0])

    def stages(self, p: NDArray[np.float64]) -> list[_Stage]:
        """The chain from rotor to load in units of Kt (see the module note)."""
        nr = self.rotor_teeth
        w1 = 2.0 * math.pi * math.exp(self._scalar(p, "log_rotor_hz"))
        inertia = nr / (w1 * w1)  # μ with rotor (and rigidly attached mass) on Nr·I at 1 A
        damping = 2.0 * self._scalar(p, "rotor_damping_ratio") * inertia * w1
        resonant = Effect.LOAD_RESONANCE in self.spec.effects
        if resonant:
            frac = self._scalar(p, "coupling_fraction")
            wc = 2.0 * math.pi * math.exp(self._scalar(p, "log_coupling_hz"))
            zc = self._scalar(p, "coupling_damping_ratio")
        if self.spec.chain is ChainKind.RIGID:
            if not resonant:
                return [_Stage(inertia, damping)]
            mu_d = frac * inertia
            kappa = mu_d * wc * wc
            return [
                _Stage((1 - frac) * inertia, damping, kappa, 2 * zc * math.sqrt(kappa * mu_d)),
                _Stage(mu_d, 0.0),
            ]
        n = self.gear_ratio
        mu_l = math.exp(self._scalar(p, "log_load_ratio")) * inertia / (n * n)
        wb = 2.0 * math.pi * math.exp(self._scalar(p, "log_belt_hz"))
        kb = mu_l * wb * wb
        cb = 2 * self._scalar(p, "belt_damping_ratio") * math.sqrt(kb * mu_l)
        load = _Stage(mu_l, 2.0 * self._scalar(p, "load_damping_ratio") * mu_l * wb)
        if not resonant:
            return [_Stage(inertia, damping, kb, cb, n), load]
        mu_p = frac * inertia
        kappa = mu_p * wc * wc
        return [
            _Stage((1 - frac) * inertia, damping, kappa, 2 * zc * math.sqrt(kappa * mu_p)),
            _Stage(mu_p, 0.0, kb, cb, n),
            load,
        ]

    def transfer(self, stages: Sequence[_Stage | _Stages],
                 s: NDArray[np.complex128] | None = None) -> Transfer:
        """Backwards from the load: each spring's twist carries the torque downstream of it
        (at the modelled orders unless ``s`` gives others); of many chains at once, (m, S,
        K) each, when ``stages`` holds them (``_Stages``), every number the same as each
        chain's alone (the arithmetic is elementwise)."""
        s = self.jw if s is None else np.asarray(s, dtype=np.complex128)
        last = stages[-1]
        theta_a = np.asarray(1.0 / (s * s), dtype=np.complex128)
        theta_f = np.zeros_like(theta_a)
        torque_a = np.asarray(last.inertia + last.damping / s, dtype=np.complex128)
        torque_f = np.ones_like(theta_a)
        for st in reversed(stages[:-1]):
            compliance = 1.0 / (st.spring + s * st.spring_damping)
            theta_a = (theta_a + torque_a * compliance) / st.ratio
            theta_f = (theta_f + torque_f * compliance) / st.ratio
            own = st.inertia * s * s + st.damping * s
            torque_a = own * theta_a + st.ratio * torque_a
            torque_f = own * theta_f + st.ratio * torque_f
        return Transfer(theta_a, theta_f, torque_a, torque_f)

    def sensor_response(self, p: NDArray[np.float64], beyond: bool = False
                        ) -> NDArray[np.complex128]:
        """What the sensor (its low-pass, its clock) makes of each order, (S, K); of the
        orders above the modelled ones with ``beyond``."""
        memo = self._sensor_beyond if beyond else self._sensor
        return memo.get(p, lambda: self._sensor_response(p, beyond))

    def _sensor_response(self, p: NDArray[np.float64], beyond: bool
                         ) -> NDArray[np.complex128]:
        a1 = self._scalar(p, "sensor_a1_ms") * 1e-3
        a2 = self._scalar(p, "sensor_a2_ms2") * 1e-6
        s, k = (self.jw_beyond, self.k_beyond) if beyond else (self.jw, self.k)
        out: NDArray[np.complex128] = 1.0 / (1.0 + a1 * s + a2 * s * s)
        if Effect.SENSOR_CLOCK_DRIFT in self.spec.effects:
            out = out * self.clock_factor(p, k)
        return out

    def _clock_samples(self) -> NDArray[np.float64]:
        """Sample numbers spread over each segment, (S, M), where the clock is evaluated."""
        span = self.obs.span.astype(np.float64)
        frac = (np.arange(32) + 0.5) / 32
        return span[:, :1] + (span[:, 1:] - span[:, :1]) * frac[None, :]

    def sample_delay(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """How long before its SYNC each sample was taken (s), at ``_clock_n``, for a
        sensor that stamps its own samples: its clock, off by δ, drifts without bound.
        (One that holds its latest sample per SYNC lags by a sawtooth of one period
        instead, integrated exactly in ``_sawtooth_factor``.) Counted from the
        recording's middle, like the sawtooth's phase."""
        t = self.obs.metadata.sync_period_s
        drift = self._scalar(p, "clock_drift_ppm") * 1e-6
        return np.asarray(-t * (self._clock_n - self.clock_middle) * drift, dtype=np.float64)

    def clock_factor(self, p: NDArray[np.float64], k: NDArray[np.float64] | None = None
                     ) -> NDArray[np.complex128]:
        """The mean of e^{-jkωd} over each segment's samples, d their delays, (S, K)."""
        k = self.k if k is None else k
        if self.spec.clock_wraps:
            return self._sawtooth_factor(p, k)
        delay = self.sample_delay(p)  # (S, M)
        # e^{-jkωd} as powers of e^{-jωd}: one exponential per sample instead of one per order.
        z = np.exp(-1j * self.obs.omega[:, None] * delay)
        top = int(k.max())
        powers = np.cumprod(np.broadcast_to(z[:, None, :], (z.shape[0], top, z.shape[1])),
                            axis=1)
        phase = powers[:, k.astype(np.intp) - 1, :]
        out: NDArray[np.complex128] = phase.mean(axis=2)
        return out

    def _sawtooth_factor(self, p: NDArray[np.float64], k: NDArray[np.float64]
                         ) -> NDArray[np.complex128]:
        """``clock_factor`` for a wrapping clock, integrated exactly (``sawtooth_mean``):
        a sum over sample points instead jumps whenever a wrap crosses one of them, and
        the fit then stalls on the steps."""
        t = self.obs.metadata.sync_period_s
        drift = self._scalar(p, "clock_drift_ppm") * 1e-6
        phase = self._scalar(p, "clock_phase")
        # Counted from the recording's middle: there a change of rate moves no sample, so
        # rate and phase are nearly independent and the fit can walk the narrow valley.
        span = self.obs.span.astype(np.float64) - self.clock_middle
        a = k[None, :] * self.obs.omega[:, None] * t  # (S, K)
        return sawtooth_mean(phase - span[:, 0] * drift, phase - span[:, 1] * drift, a)

    def _current_lag(self, p: NDArray[np.float64]) -> tuple[NDArray[np.complex128],
                                                            NDArray[np.complex128]]:
        """First-order current loop per phase at each current harmonic, (S, H) each."""
        if Effect.CURRENT_LOOP_LAG not in self.spec.effects:
            one = np.ones((self.obs.count, self.current_orders.size), dtype=np.complex128)
            return one, one
        tau = self._p(p, "current_lag_ms") * 1e-3
        s = 1j * self.obs.omega[:, None] * self.current_orders[None, :]
        return 1.0 / (1.0 + s * tau[0]), 1.0 / (1.0 + s * tau[1])

    def current_coefficients(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64],
            NDArray[np.complex128]]:
        """Each phase as DC plus harmonics: (DC (S, 1), harmonics (S, H)) for A and B."""
        return self._coefficients.get(p, lambda: self._current_coefficients(p))

    def _current_coefficients(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64],
            NDArray[np.complex128]]:
        amp_off = self._p(p, "amp_offset_mA") * 1e-3
        gain = (1.0 + self._p(p, "amp_gain_error"))[None, :] * self.trim_gain  # (S, 2)
        ga = gain[:, :1] * self.amp
        gb = gain[:, 1:] * self.amp
        lag_a, lag_b = self._current_lag(p)
        wave_a = np.zeros((self.obs.count, self.current_orders.size), dtype=np.complex128)
        wave_b = np.zeros_like(wave_a)
        wave_a[:, 0] = 1.0  # cos x
        wave_b[:, 0] = -1j  # sin x
        if self.layout.has("distortion"):
            c = self._p(p, "distortion")
            for i, h in enumerate(DISTORTION_ORDERS):
                wave_a[:, i + 1] = c[4 * i] - 1j * c[4 * i + 1]
                wave_b[:, i + 1] = (c[4 * i + 2] - 1j * c[4 * i + 3]) * np.exp(-1j * h * QUARTER)
        dc_a = self.trim_offset_A[:, :1] + amp_off[0]
        dc_b = self.trim_offset_A[:, 1:] + amp_off[1]
        return dc_a, ga * lag_a * wave_a, dc_b, gb * lag_b * wave_b

    def currents(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                        NDArray[np.float64]]:
        return self._currents.get(p, lambda: self._currents_on_grid(p))

    def _currents_on_grid(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                                 NDArray[np.float64]]:
        dc_a, ac_a, dc_b, ac_b = self.current_coefficients(p)
        i_a = dc_a + (ac_a @ self.current_synth).real
        i_b = dc_b + (ac_b @ self.current_synth).real
        if self.layout.has("dead_time"):
            dead = self._p(p, "dead_time")
            turn_a, turn_b = self.dead_time_turns(p)
            i_a, i_b = i_a - dead[0] * turn_a, i_b - dead[1] * turn_b
        return i_a, i_b

    def band_limited(self, fine: NDArray[np.float64]) -> NDArray[np.float64]:
        """A periodic waveform formed on the dead time's finer grid, cut to the orders the
        grid holds and sampled on it (the sign's harmonics fall only as 1/k: sampled on
        the grid itself they would fold back onto the low orders)."""
        spectrum = np.fft.rfft(fine, axis=-1)[..., :GRID // 2]
        out: NDArray[np.float64] = np.fft.irfft(spectrum, n=GRID, axis=-1) * (
            GRID / fine.shape[-1])
        return out

    def _currents_before_dead_time(self, p: NDArray[np.float64]
                                   ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Each phase's current before its dead time, on the dead time's finer grid."""
        dc_a, ac_a, dc_b, ac_b = self.current_coefficients(p)
        fine = self._dead_synth
        return dc_a + (ac_a @ fine).real, dc_b + (ac_b @ fine).real

    def dead_time_taken(self, p: NDArray[np.float64]
                        ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """How much of a change in each phase's current before its dead time the dead time
        takes back, on the finer grid: (D/knee)·sech²(i/knee), large only where it turns."""
        dead = self._p(p, "dead_time")
        before = self._currents_before_dead_time(p)
        out = tuple(d / self._dead_knee / np.cosh(i / self._dead_knee) ** 2
                    for d, i in zip(dead, before, strict=True))
        return out[0], out[1]

    def dead_time_turns(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64],
                                                               NDArray[np.float64]]:
        """tanh(i/knee) of each phase's current before its dead time, on the grid: the
        shape a dead-time error of one ampere takes. Formed on a grid four times finer and
        cut to the orders the grid holds: a sign's harmonics fall only as 1/k, and sampled
        on the grid itself they fold back onto the low orders."""
        before_a, before_b = self._currents_before_dead_time(p)
        return (self.band_limited(np.tanh(before_a / self._dead_knee)),
                self.band_limited(np.tanh(before_b / self._dead_knee)))

    def modulation(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """1 + ε·cos(θ + φ) averaged over each segment's mechanical angles, (S, 1)."""
        if not self.layout.has("eccentricity"):
            return np.ones((self.obs.count, 1))
        e = self._p(p, "eccentricity")
        m = self.obs.mechanical
        out: NDArray[np.float64] = (1.0 + e[0] * m.real - e[1] * m.imag)[:, None]
        return out

    def unbalance(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The off-centre rotor's load, U·sin(θ + φ) averaged over each segment's
        mechanical angles (Kt units, (S,)), with U·cos φ and U·sin φ as fractions of the
        holding torque at the largest current.

        Within one electrical period it is a constant load: it moves the rotor along its
        magnetic spring, and with it every harmonic's phase (order times the slip), from
        one trim step to the next as the rotor turns through its revolution."""
        if not self.layout.has("unbalance"):
            return np.zeros(self.obs.count)
        u = self._p(p, "unbalance") * self.largest_A
        m = self.obs.mechanical
        out: NDArray[np.float64] = u[0] * m.imag + u[1] * m.real
        return out

    def condition_mean(self, v: NDArray[np.float64]) -> NDArray[np.float64]:
        """The mean of ``v`` (…, S) over each segment's condition, at each segment."""
        cond = self.obs.condition
        conditions = len(self.obs.conditions)
        count = np.maximum(np.bincount(cond, minlength=conditions), 1)
        rows = np.atleast_2d(v)
        means = np.stack([np.bincount(cond, weights=r, minlength=conditions) / count
                          for r in rows])[:, cond]
        out: NDArray[np.float64] = means.reshape(np.shape(v))
        return out

    def saturation(self, p: NDArray[np.float64], i_a: NDArray[np.float64],
                   i_b: NDArray[np.float64]) -> NDArray[np.float64] | float:
        """Kt relative to its low-current value at the instantaneous current magnitude."""
        if not self.layout.has("saturation"):
            return 1.0
        w1, w2 = (float(v) for v in self._p(p, "saturation"))
        b1, b2 = saturation_shapes((i_a * i_a + i_b * i_b) / self.largest_A**2)
        out: NDArray[np.float64] = 1.0 - w1 * b1 - w2 * b2
        return out

    def magnet_weights(self, p: NDArray[np.float64], m: Motion
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """∂(magnet torque)/∂i_A and ∂/∂i_B on the grid: −sin θe, cos θe and the flux's."""
        pa = -m.sin_te
        pb = m.cos_te
        if self.layout.has("flux"):
            c = self._p(p, "flux")
            for i, j in enumerate(FLUX_ORDERS):
                ca, sa = m.harmonic(j)
                cb, sb = m.harmonic(j, 1)
                pa = pa - j * (c[4 * i] * sa + c[4 * i + 1] * ca)
                pb = pb - j * (c[4 * i + 2] * sb + c[4 * i + 3] * cb)
        return pa, pb

    def detent(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        if not self.layout.has("detent"):
            return np.zeros_like(m.te)
        c = self._p(p, "detent")
        out = np.zeros_like(m.te)
        for i, d in enumerate(DETENT_ORDERS):
            cd, sd = m.harmonic(d)
            out += c[2 * i] * sd + c[2 * i + 1] * cd
        return out

    @staticmethod
    def reluctance_shape(m: Motion) -> NDArray[np.float64]:
        """Eq. (3)'s τ_vr per unit of Nr·L1 with (4)-(6): ∂L/∂θ of the winding block."""
        c2, s2 = m.harmonic(2)
        return np.asarray(2.0 * c2 * m.i_a * m.i_b - s2 * (m.i_a * m.i_a - m.i_b * m.i_b),
                          dtype=np.float64)

    @staticmethod
    def unequal_reluctance_shape(m: Motion) -> NDArray[np.float64]:
        """The torque of phases whose reluctance varies unequally, per unit of Nr·L1·u:
        −sin 2θe·(i_A² + i_B²), whatever the currents' direction."""
        _, s2 = m.harmonic(2)
        return np.asarray(-s2 * (m.i_a * m.i_a + m.i_b * m.i_b), dtype=np.float64)

    def torque(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """Eq. (1) in units of Kt on the grid: magnet (with saturation and the flux's
        harmonics), cogging and reluctance; eccentricity modulates the first two."""
        pa, pb = self.magnet_weights(p, m)
        magnet = m.i_a * pa + m.i_b * pb
        made = self.saturation(p, m.i_a, m.i_b) * magnet + self.detent(p, m)
        made = made * m.modulation
        if self.layout.has("reluctance"):
            made = made + self._scalar(p, "reluctance") * self.reluctance_shape(m)
            made = made + (self._scalar(p, "reluctance_unequal")
                           * self.unequal_reluctance_shape(m))
        out: NDArray[np.float64] = made
        return out

    def friction_torque(self, p: NDArray[np.float64]
                        ) -> tuple[NDArray[np.complex128], NDArray[np.float64],
                                   NDArray[np.float64]]:
        """Friction on the load evaluated on its measured velocity: per-order torque (S, K),
        how each step's friction moves with the velocity at its three grid points
        (S, 3, N: ``friction_response``), and mean torque (S,)."""
        shapes = self.friction_shapes_here(p)
        c = self._p(p, "friction_coulomb")
        force = c[0] * shapes[0] + c[1] * shapes[1]
        slope = c[0] * shapes[2] + c[1] * shapes[3]  # (S, 3, N)
        # The load's viscous part is in the chain already, as the load stage's damping.
        return self.analysed_cells(force), slope, force.mean(axis=1)

    def load_velocity(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The load's angular velocity on the grid: its mean plus the measured ripple, the
        orders above K included as in the rotor's swing.

        Where a rough ripple nearly stops the load, those orders decide when friction
        turns. Without them, development trial friction+sensor_clock_drift@101 (a disk)
        left 24,372 of held-out χ² with both groups fitted; with them 6,239 (nominal
        542,113 for 1,752 values), and the diagnosis names the clock beside friction.
        """
        _, alpha, above = self._alpha.get(p, lambda: self._load_motion(p))
        ripple = ((alpha / self.jw) @ self.synth).real
        if above is not None:
            ripple = ripple + ((above / self.jw_beyond) @ self.synth_beyond).real
        out: NDArray[np.float64] = self.load_speed + ripple
        return out

    def friction_shapes_here(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        """``friction_shapes`` on the load's velocity at ``p`` (kept: the torque and the
        linear design both ask for it at the same point)."""
        return self._friction_shapes.get(
            p, lambda: self.friction_shapes(p, self.load_velocity(p)))

    def friction_shapes(self, p: NDArray[np.float64], velocity: NDArray[np.float64]
                        ) -> tuple[NDArray[np.float64], ...]:
        """Coulomb friction per unit of its forward and reverse levels, and their slopes.

        A smoothed sign, tanh(v/ε), splits into a forward part (1 + tanh)/2 and a
        reverse part (1 − tanh)/2 so the two directions may differ; ε is relative to
        the slowest mean load speed of the recording (``FRICTION_SMOOTHING_MAX``).

        Each grid value is the shape's mean over its grid step, the velocity taken as
        straight between grid points (``_cell_means``), not its value at the point.
        Where ε is far below the velocity's change over a step (a load whose swing
        stops it), a point value is a sampled jump: it moved only when a point crossed
        zero, and the mean slope, sech² at 48 points, swung between nothing and 1/ε as a
        point fell near the crossing. On development friction @1850757460 (the load
        reversing in one segment of 88) a sensor delay 0.01 ms longer moved that
        segment's χ² from 47 to 86,219, and every estimate held out beside it with it.
        """
        scale = float(np.min(np.abs(self.obs.load_speed)))
        eps = math.exp(self._scalar(p, "log_friction_smoothing")) * scale
        mean_t, mean_t2, slope_t, slope_t2 = _cell_means(velocity, eps)
        fwd = 0.5 * (mean_t + mean_t2)
        rev = 0.5 * (mean_t - mean_t2)
        return fwd, rev, 0.5 * (slope_t + slope_t2), 0.5 * (slope_t - slope_t2)

    def analysed_cells(self, grid: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Orders 1..K of a shape given as its means over the grid's steps: a step's mean
        keeps sin(x)/x of an order, x = πk/N, which is given back."""
        out: NDArray[np.complex128] = self.analysed(grid) / self._cell_gain
        return out

    def motion(self, p: NDArray[np.float64]) -> Motion:
        """The measured motion carried back to the rotor, and the currents driving it.

        The last one is kept: a Jacobian asks for the residuals and the linear design at
        the same parameters, and the motion is most of either's cost.
        """
        if self._last is not None and np.array_equal(self._last[0], p):
            return self._last[1]
        out = self._motion(p)
        self._last = (p.copy(), out)
        return out

    def measured(self, p: NDArray[np.float64]) -> tuple[NDArray[np.complex128],
                                                        NDArray[np.complex128] | None]:
        """The tangential harmonics as the fixture made them, orders 1..K and beyond:
        the recording's own, with the sensor's bend undone when the model has one."""
        below, above = self.obs.phasors, self.beyond
        k = self.obs.orders
        if self.radial is not None:
            # A turned element reads cos α·a_t + sin α·a_r: the radial part taken out, and
            # the cos α with it (the radius is known, so the swing fixes the scale).
            mix = self._scalar(p, "axis_mix")
            turn = math.sqrt(max(1.0 - mix * mix, 1e-6))
            below = (below - mix * self.radial[:, :k]) / turn
            if above is not None:
                above = (above - mix * self.radial[:, k:]) / turn
        if self.bend is not None:
            c2, c3 = self._p(p, "sensor_bend")
            undo = c2 * self.bend[0] + c3 * self.bend[1]
            below = below - undo[:, :k]
            if above is not None:
                above = above - undo[:, k:]
        return below, above

    def _load_motion(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128], NDArray[np.complex128] | None]:
        """The sensor's response, and the load's acceleration per order it says the
        measurement was, below and above the modelled orders."""
        sensor = self.sensor_response(p)
        below, beyond = self.measured(p)
        alpha = below / (sensor * self.radius)
        above = (None if beyond is None
                 else beyond / (self.sensor_response(p, beyond=True) * self.radius))
        return sensor, alpha, above

    def _chain_transfer(self, p: NDArray[np.float64]) -> Chain:
        """The chain at ``p`` (``Chain``)."""
        stages = self.stages(p)
        above = None if self.beyond is None else self.transfer(stages, self.jw_beyond).a
        return self.transfer(stages), above, self._drag(stages)

    def chains(self, p: NDArray[np.float64], points: list[NDArray[np.float64]]
               ) -> list[Chain | None]:
        """The chain at each of ``points`` whose chain parameters differ from ``p``'s, made
        in one batch (None for the others: theirs is ``p``'s).

        A Jacobian's chain columns each need a chain a step away, and one chain's transfer
        is a few dozen operations on arrays of a few hundred values, each paying numpy's
        call overhead: made one at a time, a belt's chains were an eighth of its
        diagnosis (development load_resonance@202, profiled), most of them a Jacobian's."""
        index = self._chain.index
        key = p[index]
        moved = [i for i, x in enumerate(points) if not np.array_equal(x[index], key)]
        out: list[Chain | None] = [None] * len(points)
        if not moved:
            return out
        each = [self.stages(points[i]) for i in moved]
        batch = [_Stages.of([stages[j] for stages in each]) for j in range(len(each[0]))]
        shape = (len(moved), *self.jw.shape)
        t = self.transfer(batch)
        a, b, c, d = (np.broadcast_to(x, shape) for x in (t.a, t.b, t.c, t.d))
        above = None
        if self.beyond is not None:
            above = np.broadcast_to(self.transfer(batch, self.jw_beyond).a,
                                    (len(moved), *self.jw_beyond.shape))
        for n, (i, stages) in enumerate(zip(moved, each, strict=True)):
            out[i] = (Transfer(a[n], b[n], c[n], d[n]), None if above is None else above[n],
                      self._drag(stages))
        return out

    def _motion(self, p: NDArray[np.float64]) -> Motion:
        x = self._inputs(p)
        transfer = x.transfer
        theta = transfer.a * x.alpha + transfer.b * x.friction
        ripple = (theta @ self.synth).real  # rotor angle ripple on the grid (mech. rad)
        if x.swing_above is not None:
            ripple = ripple + (x.swing_above @ self.synth_beyond).real
        te = self.x[None, :] - x.rho[:, None] + self.rotor_teeth * ripple
        sin_te, cos_te = np.sin(te), np.cos(te)
        first = Motion(x.alpha, x.sensor, transfer, x.friction, x.friction_slope, te, sin_te,
                       cos_te, x.i_a, x.i_b, x.modulation, x.taken, np.zeros(self.obs.count))
        # One angle per segment: its grid's sines are rotated, not evaluated again (the
        # trigonometry on the grid is most of a motion's own cost).
        return first.shifted(self.trim_lag(p, first))

    def _inputs(self, p: NDArray[np.float64], chain: Chain | None = None) -> _Inputs:
        """The motion's inputs at ``p``, its ``chain`` made already if given (``chains``)."""
        sensor, alpha, above = self._alpha.get(p, lambda: self._load_motion(p))
        transfer, theta_above, drag = (self._chain.get(p, lambda: self._chain_transfer(p))
                                       if chain is None else chain)
        force, slope, mean_force = self._friction.get(
            p, lambda: self.friction_torque(p))
        unbalance = self.unbalance(p)
        taken = drag + unbalance + self.gear_ratio * mean_force
        swing_above = None if above is None or theta_above is None else theta_above * above
        i_a, i_b = self.currents(p)
        return _Inputs(sensor, alpha, transfer, swing_above, force, slope, taken,
                       self._p(p, "load_angle_rad")[self.obs.condition], i_a, i_b,
                       self.modulation(p), unbalance)

    def trim_lag(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """How far each segment's rotor sits from its condition's load angle (electrical
        rad, (S,)): a trim step changes the mean torque the currents make on the swinging
        rotor (offsets and gain errors beating with the swing at orders 1 and 2), and the
        rotor slips along its magnetic spring until the mean torque again equals what the
        chain takes at that speed, the same for every segment of the condition but for an
        off-centre rotor's load (``unbalance``), which changes with each segment's
        mechanical angle.

        Near a mode that torque is several percent of the holding torque and moves with
        every step (a belt at 390 mA beside its 23 Hz mode: the condition's spread of it was
        21 times the balance's floor), so one angle per condition left the torque balance
        and the harmonics' phases wrong by as much. One Newton step along the spring from
        the condition's angle; the condition's mean torque, which its angle sets against
        the chain's drag, is kept.
        """
        made = self.torque(p, m).mean(axis=1)
        stiff = self.torque_slope(p, m).mean(axis=1)
        level = self.condition_mean(made)
        # The slope is −I·cos ρ (a restoring spring): the lag that brings each segment's
        # torque to its condition's level, capped where the spring is too soft to say.
        safe = np.where(np.abs(stiff) > TRIM_LAG_SOFTEST * self.amp[:, 0], stiff, np.inf)
        if self.layout.has("unbalance"):
            load = self.unbalance(p)
            level = level + load - self.condition_mean(load)
        shift = (level - made) / safe
        out: NDArray[np.float64] = np.clip(shift, -TRIM_LAG_MAX, TRIM_LAG_MAX)
        return out

    def torque_slope(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """∂(torque made)/∂θe on the grid, every term included: the magnetic spring."""
        da = -m.cos_te
        db = -m.sin_te
        if self.layout.has("flux"):
            c = self._p(p, "flux")
            for i, j in enumerate(FLUX_ORDERS):
                ca, sa = m.harmonic(j)
                cb, sb = m.harmonic(j, 1)
                da = da - j * j * (c[4 * i] * ca - c[4 * i + 1] * sa)
                db = db - j * j * (c[4 * i + 2] * cb - c[4 * i + 3] * sb)
        slope = self.saturation(p, m.i_a, m.i_b) * (m.i_a * da + m.i_b * db)
        if self.layout.has("detent"):
            c = self._p(p, "detent")
            for i, d in enumerate(DETENT_ORDERS):
                cd, sd = m.harmonic(d)
                slope = slope + d * (c[2 * i] * cd - c[2 * i + 1] * sd)
        slope = slope * m.modulation
        if self.layout.has("reluctance"):
            lam = self._scalar(p, "reluctance")
            c2, s2 = m.harmonic(2)
            slope = slope + lam * (-4.0 * s2 * m.i_a * m.i_b - 2.0 * c2 * (m.i_a**2 - m.i_b**2))
            unequal = self._scalar(p, "reluctance_unequal")
            slope = slope - unequal * 2.0 * c2 * (m.i_a**2 + m.i_b**2)
        out: NDArray[np.float64] = slope
        return out

    def chain_response(self, m: Motion) -> tuple[NDArray[np.complex128],
                                                  NDArray[np.complex128]]:
        """Rotor angle and torque needed per unit of the load's acceleration, (S, K) each,
        friction linearised about its mean slope: the size of each order's balance
        (``magnification``). The step takes friction's whole derivative
        (``rotor_response``)."""
        t = m.transfer
        # A velocity moved alike at every point moves each step's friction by its band's sum.
        drag = m.friction_slope.sum(axis=1).mean(axis=1)[:, None] / self.jw
        return t.a + t.b * drag, t.c + t.d * drag

    def friction_response(self, slope: NDArray[np.float64], x: NDArray[np.complex128]
                          ) -> NDArray[np.complex128]:
        """The change of friction's harmonics for a change ``x`` of the load's acceleration
        harmonics, (…, S, K), given how each step's friction moves with its three grid
        points' velocities, ``slope`` (…, S, 3, N): the model's own derivative.

        Friction's slope varies over the period as the spring's does, and far more where
        the load's swing nearly stops it, so a velocity change at one order makes
        friction at every other. With its mean alone (a drag per order) the step was not
        the error's derivative there, and the measurement's noise reached the residuals
        unweighed: on a development disk whose load nearly stopped in one segment of 71
        (friction @1850757460) that segment set the sensor's delay, and its condition,
        fitted to 254, was held out at 724,963 (5,236 for the whole model with this).
        """
        # Segments whose load never nears a stop have no slope (``_cell_means``): nothing
        # moves there, and only the others are made.
        live = np.any(slope, axis=(-2, -1))
        live = live.reshape(-1, live.shape[-1]).any(axis=0)  # (S,)
        if live.all():
            return self._friction_response(slope, x, self.jw)
        out = np.zeros((*np.broadcast_shapes(x.shape[:-2], slope.shape[:-3]), *self.jw.shape),
                       dtype=np.complex128)
        if live.any():
            x_live = x if x.shape[-2] == 1 else x[..., live, :]
            out[..., live, :] = self._friction_response(slope[..., live, :, :], x_live,
                                                        self.jw[live])
        return out

    def _friction_response(self, slope: NDArray[np.float64], x: NDArray[np.complex128],
                           jw: NDArray[np.complex128]) -> NDArray[np.complex128]:
        dv = ((x / jw) @ self.synth).real  # (…, S, N)
        moved = (slope[..., 0, :] * np.roll(dv, 1, axis=-1) + slope[..., 1, :] * dv
                 + slope[..., 2, :] * np.roll(dv, -1, axis=-1))
        return self.analysed_cells(moved)

    def rotor_response(self, m: Motion, x: NDArray[np.complex128]) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128]]:
        """The rotor angle's and the needed torque's change for a change ``x`` of the
        load's acceleration (S, K), friction moving with the load's velocity."""
        t = m.transfer
        force = self.friction_response(m.friction_slope, x)
        return t.a * x + t.b * force, t.c * x + t.d * force

    def error(self, p: NDArray[np.float64], m: Motion,
              made_grid: NDArray[np.float64] | None = None) -> NDArray[np.complex128]:
        """Torque the model makes minus torque the motion needs, per order, (S, K)."""
        made = self.analysed(self.torque(p, m) if made_grid is None else made_grid)
        t = m.transfer
        out: NDArray[np.complex128] = made - (t.c * m.alpha + t.d * m.friction)
        return out

    def analysed(self, grid: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Orders 1..K of real values on the grid, (…, K): one real product, where the
        complex one would first copy every value to a complex number."""
        k = self.obs.orders
        flat = grid.reshape(-1, GRID) @ self._analyse_parts
        out: NDArray[np.complex128] = (flat[:, :k] + 1j * flat[:, k:]).reshape(
            *grid.shape[:-1], k)
        return out

    def step_matrix(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """The derivative ``Step`` inverts: d(error)/d(α) with the spring's variation over the
        period, which couples order k to orders k ± h through the slope's harmonic h,
        (S, 2K, 2K) on [Re; Im].

        The rotor's swing δθ_j at order j meets the slope's harmonics s_h on the grid:
        δ(torque)_k = Nr·Σ_j (s_{k−j}·δθ_j + s_{k+j}·conj δθ_j); with friction, the swing and
        the need couple the orders too, through friction's own derivative
        (``friction_response``).
        """
        k = self.obs.orders
        s = self.torque_slope(p, m) @ self.slope_analyse  # s_h, h = 0 … 2K, (S, 2K + 1)
        both = np.concatenate([np.conj(s[:, :0:-1]), s], axis=1)[:, self.order_pairs]
        # d(error)/dα = spring·(rotor per α) − need per α, each a real map on [Re; Im]
        # (``rotor_response``, whose friction couples the orders).
        basis = np.concatenate([np.eye(k), 1j * np.eye(k)]).astype(np.complex128)
        theta, need = self.rotor_response(m, basis[:, None, :])  # (2K, S, K)
        spring = _real_map(self.rotor_teeth * both[:, 0], self.rotor_teeth * both[:, 1])
        return np.asarray(spring @ _stacked(theta) - _stacked(need), dtype=np.float64)

    def step(self, p: NDArray[np.float64], m: Motion, near: Step | None = None) -> Step:
        """The Newton step at ``p`` (``Step``), its derivative inverted afresh, or with
        ``near`` (a step a difference away) that step's inverse refined by Newton–Schulz
        (``NEAR_REFINE``): a Jacobian's differenced columns would otherwise invert every
        segment's matrix again, most of an evaluation's cost."""
        matrix = self.step_matrix(p, m)
        inverse = None
        if near is not None:
            inverse = near.inverse
            eye = np.eye(matrix.shape[1])
            for _ in range(NEAR_REFINE):
                # X ← X·(2I − M·X) squares the error I − M·X.
                left = eye - matrix @ inverse
                size = float(np.max(np.abs(left)))
                if size > NEAR_START:
                    inverse = None
                    break
                inverse = inverse + inverse @ left
                if size * size < NEAR_DONE:  # what is left after this pass
                    break
        if inverse is None:
            inverse = np.asarray(np.linalg.inv(matrix), dtype=np.float64)
        return Step(inverse, self.radius * m.sensor * self.weight)

    def residuals_near(self, p: NDArray[np.float64], base: NDArray[np.float64]
                       ) -> NDArray[np.float64]:
        """``residuals`` at ``p``, a difference step from ``base``, the step refined from
        ``base``'s (``step``). Not kept: ``residuals`` keeps the exact."""
        m = self.motion(p)
        return self._residuals_of(p, m, self.torque(p, m),
                                  self.step(p, m, near=self.made_and_step(base)[1]))

    # ------------------------------------------------------------------ linear part
    def linear_index(self) -> NDArray[np.intp]:
        return self.layout.indices(BlockKind.LINEAR)

    def linear_bases(self, p: NDArray[np.float64], m: Motion) -> list[NDArray[np.float64]]:
        """∂(torque made)/∂β on the grid for each torque-side linear parameter β, in
        layout order; friction's (which act on the needed torque) come separately."""
        lay = self.layout
        pa, pb = self.magnet_weights(p, m)
        magnet = m.i_a * pa + m.i_b * pb
        sat = self.saturation(p, m.i_a, m.i_b)
        mod = m.modulation
        dsat_a: NDArray[np.float64] | float = 0.0
        dsat_b: NDArray[np.float64] | float = 0.0
        if lay.has("saturation"):
            w1, w2 = self._p(p, "saturation")
            s1, s2 = saturation_slopes((m.i_a**2 + m.i_b**2) / self.largest_A**2)
            # d(Kt)/d(i) = d(Kt)/d(u²) · 2i/I_max²
            g = -2.0 * (w1 * s1 + w2 * s2) / self.largest_A**2
            dsat_a, dsat_b = g * m.i_a, g * m.i_b
        d_ia = mod * (sat * pa + dsat_a * magnet)
        d_ib = mod * (sat * pb + dsat_b * magnet)
        if lay.has("reluctance"):
            lam = self._scalar(p, "reluctance")
            c2, s2 = m.harmonic(2)
            unequal = self._scalar(p, "reluctance_unequal")
            d_ia = d_ia + lam * (2.0 * c2 * m.i_b - 2.0 * s2 * m.i_a) - unequal * 2.0 * s2 * m.i_a
            d_ib = d_ib + lam * (2.0 * c2 * m.i_a + 2.0 * s2 * m.i_b) - unequal * 2.0 * s2 * m.i_b
        _, ac_a, _, ac_b = self.current_coefficients(p)
        taken = self.dead_time_taken(p) if lay.has("dead_time") else None

        def kept(phase: int, base: NDArray[np.float64], d_i: NDArray[np.float64],
                 fine: NDArray[np.float64] | float) -> NDArray[np.float64]:
            # ``base``: a change of a phase's current before its dead time times the torque
            # per ampere; as the phase carries it, less what the dead time takes back where
            # the current turns (``fine``: the change on the dead time's finer grid).
            if taken is None:
                return base
            out: NDArray[np.float64] = base - d_i * self.band_limited(taken[phase] * fine)
            return out

        bases: list[NDArray[np.float64]] = []
        for block in lay.blocks:
            if block.kind is not BlockKind.LINEAR:
                continue
            name = block.name
            if name == "amp_offset_mA":
                bases += [kept(0, 1e-3 * d_ia, d_ia, 1e-3), kept(1, 1e-3 * d_ib, d_ib, 1e-3)]
            elif name == "amp_gain_error":
                gain = 1.0 + self._p(p, "amp_gain_error")
                fine = self._dead_synth
                bases += [kept(0, d_ia * (ac_a @ self.current_synth).real / gain[0], d_ia,
                               (ac_a @ fine).real / gain[0]),
                          kept(1, d_ib * (ac_b @ self.current_synth).real / gain[1], d_ib,
                               (ac_b @ fine).real / gain[1])]
            elif name == "distortion":
                lag_a, lag_b = self._current_lag(p)
                ga = (1.0 + self._p(p, "amp_gain_error")[0]) * self.trim_gain[:, :1] * self.amp
                gb = (1.0 + self._p(p, "amp_gain_error")[1]) * self.trim_gain[:, 1:] * self.amp
                for i, h in enumerate(DISTORTION_ORDERS):
                    za = ga[:, 0] * lag_a[:, i + 1]
                    zb = gb[:, 0] * lag_b[:, i + 1] * np.exp(-1j * h * QUARTER)
                    wave = self.current_synth[i + 1][None, :]
                    fine = self._dead_synth[i + 1][None, :]
                    for phase, z, d_i in ((0, za, d_ia), (1, zb, d_ib)):
                        for turn in (1.0, -1j):
                            bases.append(kept(phase, d_i * (turn * z[:, None] * wave).real, d_i,
                                              (turn * z[:, None] * fine).real))
            elif name == "dead_time":
                turn_a, turn_b = self.dead_time_turns(p)
                bases += [-d_ia * turn_a, -d_ib * turn_b]
            elif name == "flux":
                scale = mod * sat
                for j in FLUX_ORDERS:
                    ca, sa = m.harmonic(j)
                    cb, sb = m.harmonic(j, 1)
                    bases += [-j * scale * m.i_a * sa, -j * scale * m.i_a * ca,
                              -j * scale * m.i_b * sb, -j * scale * m.i_b * cb]
            elif name == "detent":
                for d in DETENT_ORDERS:
                    cd, sd = m.harmonic(d)
                    bases += [mod * sd, mod * cd]
            elif name == "reluctance":
                bases.append(self.reluctance_shape(m))
            elif name == "reluctance_unequal":
                bases.append(self.unequal_reluctance_shape(m))
            elif name == "saturation":
                b1, b2 = saturation_shapes((m.i_a**2 + m.i_b**2) / self.largest_A**2)
                bases += [-mod * b1 * magnet, -mod * b2 * magnet]
            elif name == "eccentricity":
                inner = sat * magnet + self.detent(p, m)
                mech = self.obs.mechanical[:, None]
                bases += [mech.real * inner, -mech.imag * inner]
            elif name == "friction_coulomb":
                bases += [np.zeros_like(m.te)] * block.size  # filled in linear_design
        return bases

    def linear_design(self, p: NDArray[np.float64]
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(weighted residuals at zero linear parameters, d residuals / d linear
        parameter, (L, n)), laid out as ``residuals``.

        Each segment's slip and the error's scale are held where ``p`` leaves them
        (``linear_jacobian`` moves them too), and the bases of products (flux,
        distortion, saturation, reluctance with the currents) use the current iterate:
        a couple of passes settle what that leaves.
        """
        return self._linear_design(p)[:2]

    def _linear_design(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """``linear_design``, and the torque bases it was made from, (n, S, N)."""
        m = self.motion(p)
        bases = self.linear_bases(p, m)
        stacked = np.stack(bases) if bases else np.zeros((0, *m.te.shape))
        harmonic = self.analysed(stacked)
        dc = stacked.mean(axis=2)
        lay = self.layout
        shapes = self.friction_shapes_here(p)
        order = [b.name for b in lay.blocks if b.kind is BlockKind.LINEAR]
        row = sum(lay.block(n).size for n in order[:order.index("friction_coulomb")])
        for j in (0, 1):
            harmonic[row + j] = -m.transfer.d * self.analysed_cells(shapes[j])
            dc[row + j] = -self.gear_ratio * shapes[j].mean(axis=1)
        made, step = self.made_and_step(p)
        dc_scale = self.dc_weight()
        beta = p[self.linear_index()]
        err = self.error(p, m, made) - np.tensordot(beta, harmonic, axes=1)
        err_dc = self.dc_error(p, m, made) - beta @ dc
        # The prior is linear in the gain errors: its row is their mean over its σ.
        prior = np.zeros((len(beta), 1))
        gains = [i for i, n in enumerate(self._linear_names()) if n == "amp_gain_error"]
        prior[gains, 0] = 0.5 / COMMON_GAIN_SIGMA
        at_zero = self._flatten(step.apply(err), err_dc * dc_scale, np.zeros(1))
        design = np.array([self._flatten(h, d * dc_scale, q) for h, d, q in
                           zip(step.apply(harmonic), dc, prior, strict=True)]
                          ).reshape(len(beta), -1)
        return at_zero, design, stacked

    def linear_jacobian(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """d residuals / d linear parameter, (n, L), the friction levels' excepted
        (``motion_index``).

        ``linear_design`` holds each segment's slip (``trim_lag``) and the error's scale
        where the current point left them, which is what a linear solve at fixed
        nonlinear parameters wants, but not a Jacobian: a torque term also moves the
        rotor along its spring and stiffens or softens that spring, and for a reluctance
        torque, whose ripple at constant current is small, those are most of what it
        does. Its design column was 37 % off and its gradient of the wrong sign, and the
        solver stopped on a clean nominal fit 135 in χ² short of the reluctance a
        development trial held (reluctance_torque@1517242068).

        Both enter through two numbers per segment, so each parameter's share follows by
        the chain rule from its torque basis and that basis's slope along the rotor angle
        (the basis one step along it, differenced: the bases are smooth in the angle).
        """
        _, design, bases = self._linear_design(p)
        lin = self.linearised(p)
        m, first = lin.motion, lin.first

        def slopes_of(here: NDArray[np.float64], at: Motion) -> NDArray[np.float64]:
            along = np.stack(self.linear_bases(p, at.shifted(ANGLE_STEP)))
            out: NDArray[np.float64] = (along - here) / ANGLE_STEP
            return out

        slopes = slopes_of(bases, m)
        bases1 = np.stack(self.linear_bases(p, first))
        slopes1 = slopes_of(bases1, first)
        d_lag = self._slip_change(lin, bases1.mean(axis=2), slopes1.mean(axis=2))
        # What the slip and the spring change: the torque made, and the step. The step's
        # own change, −step·(d matrix)·step(error), is the torque the changed spring makes
        # on the swing the step already asks for.
        d_slope = slopes + d_lag[:, :, None] * lin.bend[None]
        d_error = (d_lag[:, :, None] * self.analysed(lin.slope)[None]
                   - self.rotor_teeth * self.analysed(d_slope * lin.swing[None]))
        d_dc = d_lag * lin.slope.mean(axis=1)
        dc_weight = self.dc_weight()
        extra = np.array([self._flatten(h, d * dc_weight, np.zeros(1))
                          for h, d in zip(lin.step.apply(d_error), d_dc, strict=True)])
        out: NDArray[np.float64] = design + extra.reshape(design.shape)
        return out

    def linearised(self, p: NDArray[np.float64]) -> _Linearised:
        return self._linear_memo.get(p, lambda: self._linearise(p))

    def _linearise(self, p: NDArray[np.float64]) -> _Linearised:
        m = self.motion(p)
        first = m.shifted(-m.lag)

        def slope_and_bend(at: Motion) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
            slope = self.torque_slope(p, at)
            return slope, (self.torque_slope(p, at.shifted(ANGLE_STEP)) - slope) / ANGLE_STEP

        slope, bend = slope_and_bend(m)
        slope1, bend1 = slope_and_bend(first)
        spring1 = slope1.mean(axis=1)
        acts = ((np.abs(spring1) > TRIM_LAG_SOFTEST * self.amp[:, 0])
                & (np.abs(m.lag) < TRIM_LAG_MAX))
        made, step = self.made_and_step(p)
        alpha = step.alpha(self.error(p, m, made))
        swing = (self.rotor_response(m, alpha)[0] @ self.synth).real
        return _Linearised(m, first, slope, bend, slope1, bend1, acts, step, alpha, swing)

    def _slip_change(self, lin: _Linearised, d_made1: NDArray[np.float64],
                     d_spring1: NDArray[np.float64],
                     d_load: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """How far each segment's slip (``trim_lag``: (level − made)/spring on the motion
        before it, where it acts) moves, (P, S), for changes of the torque made and of the
        spring there, and of an off-centre rotor's load (which moves the level), (P, S)
        each."""
        d_level = self.condition_mean(d_made1)
        if d_load is not None:
            d_level = d_level + d_load - self.condition_mean(d_load)
        safe = np.where(lin.acts, lin.spring1, np.inf)
        out: NDArray[np.float64] = (d_level - d_made1 - lin.motion.lag * d_spring1) / safe
        return out

    def motion_columns(self, p: NDArray[np.float64], points: list[NDArray[np.float64]],
                       steps: NDArray[np.float64]) -> NDArray[np.float64]:
        """d residuals / d parameter, (n, P), for parameters that enter only a motion's
        inputs (``_Inputs``: the chain, the sensor, the friction, the load angles), each
        given as ``p`` moved by its ``steps`` entry (``points``).

        The inputs are differenced centrally (they are cheap) and carried through the rest
        by the chain rule: the rotor's swing moves its angle on the grid, and with it the torque
        made (the spring), the slip (``trim_lag``) and the spring itself, which changes
        the step (−step·(d matrix)·step(error), as in ``linear_jacobian``). Differenced
        through the whole evaluation instead, each column cost a motion, a torque and
        an inverted step matrix per segment: most of a fit's time. A point that moves
        the currents or the torque's own parameters is differenced whole.
        """
        lin = self.linearised(p)
        m = lin.motion
        here = self._inputs(p)
        index = self._torque_index
        opposite = [2.0 * p - x for x in points]
        chains = self.chains(p, [*points, *opposite])
        inputs = [self._inputs(x, c) for x, c in zip(points, chains[:len(points)],
                                                     strict=True)]
        mirrored = [self._inputs(x, c) for x, c in zip(opposite, chains[len(points):],
                                                       strict=True)]
        whole = [i for i, (x, q) in enumerate(zip(inputs, points, strict=True))
                 if not (np.array_equal(q[index], p[index]) and np.array_equal(x.i_a, here.i_a)
                         and np.array_equal(x.i_b, here.i_b)
                         and np.array_equal(x.modulation, here.modulation))]
        h = np.asarray(steps, dtype=np.float64)

        def d(pick: Callable[[_Inputs], NDArray[Any]]) -> NDArray[Any]:
            # Each point's step, along the first axis of whatever the input's shape is.
            per_point = h.reshape(-1, *([1] * pick(here).ndim))
            out: NDArray[Any] = (np.stack([pick(x) for x in inputs])
                                 - np.stack([pick(x) for x in mirrored])) / (2.0 * per_point)
            return out

        t = m.transfer
        d_a, d_b = d(lambda x: x.transfer.a), d(lambda x: x.transfer.b)
        d_c, d_d = d(lambda x: x.transfer.c), d(lambda x: x.transfer.d)
        d_alpha, d_force = d(lambda x: x.alpha), d(lambda x: x.friction)
        d_theta = d_a * m.alpha + t.a * d_alpha + d_b * m.friction + t.b * d_force
        d_ripple = (d_theta @ self.synth).real
        if here.swing_above is not None:
            above = here.swing_above

            def swing_above(x: _Inputs) -> NDArray[np.complex128]:
                return above if x.swing_above is None else x.swing_above

            d_ripple = d_ripple + (d(swing_above) @ self.synth_beyond).real
        nr = self.rotor_teeth
        d_te1 = nr * d_ripple - d(lambda x: x.rho)[:, :, None]
        d_lag = self._slip_change(lin, (lin.slope1 * d_te1).mean(axis=2),
                                  (lin.bend1 * d_te1).mean(axis=2),
                                  d(lambda x: x.unbalance) if self.layout.has("unbalance")
                                  else None)
        d_te = d_te1 + d_lag[:, :, None]
        d_made = lin.slope * d_te
        # The chain's response and need to the step's acceleration (``rotor_response``).
        moved_theta, moved_need = d_a * lin.alpha, d_c * lin.alpha
        force = self.friction_response(m.friction_slope, lin.alpha)
        d_force_step = self.friction_response(d(lambda x: x.friction_slope), lin.alpha)
        moved_theta = moved_theta + d_b * force + t.b * d_force_step
        moved_need = moved_need + d_d * force + t.d * d_force_step
        d_need = d_c * m.alpha + t.c * d_alpha + d_d * m.friction + t.d * d_force
        moved_swing = (moved_theta @ self.synth).real
        d_step_torque = (nr * self.analysed(lin.bend * d_te * lin.swing
                                            + lin.slope * moved_swing)
                         - moved_need)
        d_error = self.analysed(d_made) - d_need
        factor = self.radius * self.weight
        harmonic = (d(lambda x: x.sensor) * factor * lin.alpha
                    + lin.step.apply(d_error - d_step_torque))
        dc = ((d_made.mean(axis=2) - d(lambda x: x.taken)) * self.dc_weight())
        prior = self.prior(p)
        out = np.stack([self._flatten(harmonic[i], dc[i],
                                      (self.prior(q) - prior) / steps[i])
                        for i, q in enumerate(points)], axis=1)
        if whole:
            base = self.residuals(p)
            for i in whole:
                out[:, i] = (self.residuals_near(points[i], p) - base) / steps[i]
        return out

    def motion_index(self) -> NDArray[np.intp]:
        """Parameters whose Jacobian columns come through the motion's inputs
        (``motion_columns``): the nonlinear ones, and the friction levels, which move the
        load's swing and with it every rotor angle of the grid."""
        out = [self.layout.indices(BlockKind.NONLINEAR),
               np.arange(self.layout.size)[self.layout.slices["friction_coulomb"]]]
        return np.sort(np.concatenate(out))

    def _linear_names(self) -> list[str]:
        return [b.name for b in self.layout.blocks if b.kind is BlockKind.LINEAR
                for _ in range(b.size)]

    def prior(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """What the drive's datasheet says without the recording: its current amplitude is
        calibrated to a few percent. Only the gains' mean is held to that (their split is
        what the recording measures): alone it is weakly identified (it trades against
        the rotor's frequency), and a fit would wander along that valley."""
        common = float(np.mean(self._p(p, "amp_gain_error")))
        return np.array([common / COMMON_GAIN_SIGMA])

    @staticmethod
    def _flatten(harmonic: NDArray[np.complex128], dc: NDArray[np.float64],
                 prior: NDArray[np.float64]) -> NDArray[np.float64]:
        return np.concatenate([harmonic.real.ravel(), harmonic.imag.ravel(), dc, prior])

    # ------------------------------------------------------------------ the DC balance
    def dc_weight(self) -> NDArray[np.float64]:
        """1/σ of each segment's torque balance: the model floor of the holding torque
        (0 where the model leaves the balance out)."""
        out: NDArray[np.float64] = 1.0 / (MODEL_FLOOR * self.amp[:, 0])
        return out if self.spec.dc_balance else np.zeros_like(out)

    def _drag(self, stages: list[_Stage]) -> NDArray[np.float64]:
        """The mean torque the chain's own damping takes at each segment's speed, seen at
        the motor (Kt units): the viscous drag its ripple damping implies."""
        return self.drag_coefficient(stages) * self.obs.omega / self.rotor_teeth

    @staticmethod
    def drag_coefficient(stages: list[_Stage]) -> float:
        """The chain's viscous drag seen at the motor, Kt units per rad/s of the rotor:
        each stage's damping times its speed and its torque both geared back."""
        total, gear = 0.0, 1.0
        for st in stages:
            total += st.damping * gear * gear
            gear *= st.ratio
        return total

    def dc_error(self, p: NDArray[np.float64], m: Motion,
                 made: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
        """Mean torque made minus mean torque taken (drag, and friction when modelled),
        per segment: at constant speed they must balance."""
        grid = self.torque(p, m) if made is None else made
        out: NDArray[np.float64] = grid.mean(axis=1) - m.taken
        return out

    # ------------------------------------------------------------------ residuals
    def weighted_error(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        m = self.motion(p)
        made, step = self.made_and_step(p)
        return step.apply(self.error(p, m, made))

    def equation_error(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The error as sensor acceleration (m/s²) per segment and order, (S, K)."""
        out: NDArray[np.complex128] = self.weighted_error(p) / self.weight
        return out

    def residuals(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Weighted residuals for a least-squares solver: the harmonic errors' real and
        imaginary parts, then each segment's torque balance. (The last are kept: the
        solver asks for them, then for the Jacobian, which starts from them.)"""
        # A copy: a caller may scale or clean what it is given.
        return self._residuals.get(p, lambda: self._residuals_at(p)).copy()

    def _residuals_at(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        return self._residuals_of(p, self.motion(p), *self.made_and_step(p))

    def _residuals_of(self, p: NDArray[np.float64], m: Motion, made: NDArray[np.float64],
                      step: Step) -> NDArray[np.float64]:
        return self._flatten(step.apply(self.error(p, m, made)),
                             self.dc_error(p, m, made) * self.dc_weight(), self.prior(p))

    def made_and_step(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], Step]:
        """The torque made on the grid and the error's step, on the motion at ``p``."""
        def compute() -> tuple[NDArray[np.float64], Step]:
            m = self.motion(p)
            return self.torque(p, m), self.step(p, m)
        return self._made.get(p, compute)

    @property
    def harmonic_values(self) -> int:
        """How many of ``residuals`` are harmonic (the rest are torque balances)."""
        return 2 * self.obs.count * self.obs.orders

    def predicted(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The harmonics this model says the sensor should have measured (m/s²), (S, K)."""
        out: NDArray[np.complex128] = self.obs.phasors - self.equation_error(p)
        return out

    def in_mps2(self, weighted: NDArray[np.float64]) -> NDArray[np.float64]:
        """Weighted residuals (as ``residuals`` lays them out) back in m/s², shape (2, S, K):
        real and imaginary parts of each segment's and order's residual."""
        shaped = weighted[:self.harmonic_values].reshape(2, self.obs.count, self.obs.orders)
        out: NDArray[np.float64] = shaped / self.weight
        return out

    def residual_rows(self) -> NDArray[np.intp]:
        """Segment index of every entry of ``residuals`` (−1 for the prior, which belongs
        to no segment)."""
        segments = np.arange(self.obs.count)
        seg = np.repeat(segments, self.obs.orders)
        return np.concatenate([seg, seg, segments, [-1]])

    def noise_chi2(self) -> float:
        """What the sensor's noise alone leaves in expectation on this model's residuals:
        noise²/σ² for each part of a phasor, less than 1 where σ carries the model floor
        of a strong ripple, and 1 for each other value (a torque balance's is weighed by
        the floor itself)."""
        noise = self.obs.noise
        harmonic = float(np.sum(2.0 * noise**2 / np.maximum(self.obs.sigma, 1e-12) ** 2))
        return harmonic + (self.residual_rows().size - 2 * noise.size)

    def residual_conditions(self) -> NDArray[np.intp]:
        """Condition of every entry of ``residuals`` (−1 for the prior)."""
        rows = self.residual_rows()
        out: NDArray[np.intp] = np.where(rows >= 0, self.obs.condition[rows], -1)
        return out

    def floor(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """What the model itself is trusted to, per segment and order, m/s²: every order's
        torque balance to ``MODEL_FLOOR`` as the chain magnifies it (``magnification``),
        and the bearings' friction where what it acts on nearly stops
        (``turning_floor``)."""
        magnified = MODEL_FLOOR * np.abs(self.obs.phasors) * self.magnification(p)
        out: NDArray[np.float64] = np.hypot(magnified, self.turning_floor(p))
        return out

    def turning_floor(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The harmonics a Coulomb friction of the fitted level makes where the load or,
        beyond a belt, the rotor nearly stops, m/s² per segment and order, at
        ``FRICTION_TURN_SHARE`` of their size where the model holds that friction (the
        load) and whole where it does not (the motor's own bearings on a belt).

        A bearing's friction near zero speed is where every model of it differs (Coulomb
        smoothed or not, Stribeck, pre-sliding), and the model evaluates it on a measured
        velocity whose own error is then comparable to the speed it turns over; the sign
        is taken as turning over ``FLOOR_SMOOTHING`` of the slowest speed, whatever the
        fit's smoothing, so that a rotor or load that comes near stopping without
        reversing is covered too. A healthy disk whose load nearly stopped at each period
        of its slowest-current, fastest holds (development none@501, 310 mA at 35 Hz
        beside its rotor's mode, bearings' Coulomb 3.7 and 4.4 % of the holding torque)
        left held-out χ² 3,566 against 3,009 without that friction, 430 of it in those
        holds, and a loop lag was named there."""
        x = self._inputs(p)
        step = self.made_and_step(p)[1]
        level = float(np.mean(self._p(p, "friction_coulomb")))

        def harmonics(velocity: NDArray[np.float64], torque: float,
                      through: NDArray[np.complex128] | float = 1.0) -> NDArray[np.float64]:
            eps = FLOOR_SMOOTHING * float(np.min(np.abs(velocity.mean(axis=1))))
            sign = _cell_means(velocity, eps)[0]
            made = through * self.analysed_cells(torque * sign)
            return np.abs(step.apply(made)) / self.weight

        # At the load its friction enters through the chain (``error``: t.d·F); at the
        # rotor, as the motor's torque itself.
        load = harmonics(self.load_velocity(p), level, x.transfer.d)
        out: NDArray[np.float64] = FRICTION_TURN_SHARE * load
        if self.spec.chain is ChainKind.BELT:
            theta = x.transfer.a * x.alpha + x.transfer.b * x.friction  # rotor angle, mech rad
            speed = self.obs.omega[:, None] / self.rotor_teeth
            rotor = speed + ((self.jw * theta) @ self.synth).real
            out = np.hypot(out, harmonics(rotor, self.gear_ratio * level))
        return out

    def magnification(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """How much the chain magnifies a relative torque error into a relative
        acceleration error, per segment and order: 1 far from any mode, about twice the
        quality factor on one.

        Each order's torque balance (spring part plus need) is taken as uncertain by the
        same fraction, in a random phase, and carried through the whole Newton
        derivative (``step``), not its diagonal alone: where the swing at one order is
        large, the spring it rides makes torque at its neighbours, and their errors are
        the resonant order's error too. Near a fold of that nonlinear spring the
        derivative is nearly singular and every order of the segment is a
        hypersensitive function of the chain: on a clean development disk
        (magnetic_saturation@1306254870's twin, ζ 0.017, order 2 of one segment on the
        mode) a change of ζ by 0.6 % moved order 2 by 56 of 117 m/s² and order 3 by 17
        of 32; the diagonal put the floor of order 3 at 0.46 m/s², and holding that
        segment out missed it by 47 times as much. With one order alone the two agree.
        """
        m = self.motion(p)
        k = self.obs.orders
        theta, need = self.chain_response(m)
        stiff = self.segment_springs(p, m)[:, None]
        size = (np.abs(stiff * theta) + np.abs(need)) * np.abs(m.alpha)  # each balance, (S, K)
        inverse = self.made_and_step(p)[1].inverse
        # Re and Im of each order's error independent, each with half the variance.
        spread = 0.5 * np.concatenate([size, size], axis=1) ** 2
        variance = np.einsum("sij,sj->si", inverse * inverse, spread)
        coupled = np.sqrt(variance[:, :k] + variance[:, k:])
        moving = np.maximum(np.abs(m.alpha), 1e-12 * max(float(np.max(np.abs(m.alpha))), 1e-300))
        out: NDArray[np.float64] = np.maximum(coupled / moving, 1.0)
        return out

    # ------------------------------------------------------------------ physics out
    def segment_springs(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """Each segment's magnetic spring along its motion (Kt units per mechanical rad):
        the torque's restoring slope averaged over the grid."""
        out: NDArray[np.float64] = -np.mean(self.torque_slope(p, m), axis=1) * self.rotor_teeth
        return out

    def swing_springs(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The magnetic spring per condition as the rotor's swing rides it (Kt units per
        mechanical rad): the torque's slope averaged over the grid and the segments.

        A transient rings on the spring the motion averages, not on the static one: a
        rough development disk (none@208) swinging up to ±0.5 electrical rad rides 0.94-0.96
        of its static spring, and its mode sits 2-3 % below the one ``modes`` gives at rest.
        """
        slope = self.segment_springs(p, self.motion(p))
        count = len(self.obs.conditions)
        total = np.bincount(self.obs.condition, weights=slope, minlength=count)
        seen = np.bincount(self.obs.condition, minlength=count)
        out: NDArray[np.float64] = total / np.maximum(seen, 1)
        return out

    def rotor_hz(self, p: NDArray[np.float64], amplitude_A: float,
                 load_angle_rad: float = 0.0) -> float:
        """The rotor's own natural frequency on its magnetic spring at a current."""
        f1 = math.exp(self._scalar(p, "log_rotor_hz"))
        return f1 * math.sqrt(max(amplitude_A * math.cos(load_angle_rad), 1e-9))

    def modes(self, p: NDArray[np.float64], amplitude_A: float,
              load_angle_rad: float = 0.0, spring: float | None = None
              ) -> list[tuple[float, float]]:
        """(frequency Hz, damping ratio) of the chain on its magnetic spring at a current,
        or on ``spring`` (Kt units per mechanical rad: ``swing_springs``) where given."""
        stages = self.stages(p)
        n = len(stages)
        mass = np.diag([st.inertia for st in stages])
        stiff = np.zeros((n, n))
        damp = np.diag([st.damping for st in stages])
        stiff[0, 0] = (self.rotor_teeth * amplitude_A * math.cos(load_angle_rad)
                       if spring is None else spring)
        for i, st in enumerate(stages[:-1]):
            for matrix, coeff in ((stiff, st.spring), (damp, st.spring_damping)):
                matrix[i, i] += coeff * st.ratio * st.ratio
                matrix[i, i + 1] -= coeff * st.ratio
                matrix[i + 1, i] -= coeff * st.ratio
                matrix[i + 1, i + 1] += coeff
        inv_m = np.linalg.inv(mass)
        state = np.block([[np.zeros((n, n)), np.eye(n)], [-inv_m @ stiff, -inv_m @ damp]])
        out = []
        for lam in np.linalg.eigvals(state):
            if lam.imag > 0:
                wn = abs(lam)
                out.append((float(wn / (2 * math.pi)), float(-lam.real / wn)))
        return sorted(out)
