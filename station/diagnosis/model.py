"""The torque model of the paper, its mechanical chain, and the effects beyond it.

The model is fitted as an *equation error* on the motion the sensor measured.
Each segment's harmonics 1..K give the load's periodic motion; the chain of
inertias and springs (rigid disk, or belt) maps it back to the rotor's motion
and to the torque the rotor must have felt; the torque model, evaluated on
that same rotor motion, says what torque the currents did make. The two must
agree at every order. Evaluating the torque on the measured motion, instead of
integrating the equations of motion, keeps the rotor's large-swing
nonlinearity (a few tenths of an electrical radian at untrimmed offsets,
which puts strong 3rd to 5th harmonics into any recording) inside the model at
no cost: no nonlinear oscillation has to be solved, and the unknowns enter
almost linearly.

The disagreement at each order is divided by its sensitivity to that order's
acceleration (the linearised chain), so residuals are in m/s² like the
measurement itself and weighting them by its uncertainty makes the fit close
to the output-error maximum-likelihood one.

All torques are in units of the torque constant Kt (so in A): Kt itself and
the inertias cannot both be known from an acceleration alone, only their
ratios, and the parameters are chosen to be the identifiable ones (natural
frequencies, damping ratios, relative harmonic amplitudes).

Sign conventions follow ``station.physics.motor`` and ICD.md §2: phase A
carries cos x, phase B sin x, the rotor's electrical angle is x − ρ plus its
oscillation, and a phasor Z of order k means Re(Z·e^{jkx}).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from station.core import GAIN_UNITY, Effect
from station.diagnosis.observations import Observations

GRID = 64
"""Points per electrical period where the torque is evaluated: orders up to 31 alias-free."""

FLUX_ORDERS = (2, 3, 4, 5)
"""Harmonics j of the mutual inductances L1f, L2f (j = 1 is the fundamental)."""
DISTORTION_ORDERS = (2, 3, 4, 5)
"""Harmonics h of each phase current's waveform."""
DETENT_ORDERS = (4, 8)
"""Cogging repeats every full step: four times per electrical period, and its multiples."""

QUARTER = math.pi / 2.0

LINEAR_BLOCKS = frozenset(
    {"amp_offset_mA", "amp_gain_error", "flux", "distortion", "detent", "reluctance"}
)


class ChainKind(StrEnum):
    """The mechanics between rotor and sensor that the recording's fixture implies."""

    RIGID = "rigid"  # sensor on a disk on the shaft (gear ratio 1)
    BELT = "belt"  # sensor on a load driven through a belt (gear ratio ≠ 1)


CANDIDATES: tuple[Effect, ...] = (
    Effect.FLUX_HARMONICS,
    Effect.DETENT_TORQUE,
    Effect.CURRENT_DISTORTION,
    Effect.LOAD_RESONANCE,
    Effect.RELUCTANCE_TORQUE,
)
"""Effects the diagnosis can fit as term groups, in a fixed order (ties resolve by it)."""


@dataclass(frozen=True)
class Block:
    """A named run of parameters: where it sits, start values and bounds."""

    name: str
    size: int
    start: float | tuple[float, ...]
    low: float = -np.inf
    high: float = np.inf


@dataclass
class Layout:
    """Where each named block sits in the flat parameter vector."""

    blocks: list[Block] = field(default_factory=list)
    slices: dict[str, slice] = field(default_factory=dict)

    def add(self, block: Block) -> None:
        begin = self.size
        self.blocks.append(block)
        self.slices[block.name] = slice(begin, begin + block.size)

    @property
    def size(self) -> int:
        return sum(b.size for b in self.blocks)

    def has(self, name: str) -> bool:
        return name in self.slices

    def start(self) -> NDArray[np.float64]:
        out = np.empty(self.size)
        for b in self.blocks:
            out[self.slices[b.name]] = b.start
        return out

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        low = np.empty(self.size)
        high = np.empty(self.size)
        for b in self.blocks:
            low[self.slices[b.name]] = b.low
            high[self.slices[b.name]] = b.high
        return low, high


@dataclass(frozen=True)
class ModelSpec:
    """Which chain and which effect term groups a model carries."""

    chain: ChainKind
    effects: frozenset[Effect] = frozenset()

    def with_effect(self, effect: Effect) -> ModelSpec:
        return ModelSpec(self.chain, self.effects | {effect})


def chain_for(gear_ratio: float) -> ChainKind:
    return ChainKind.RIGID if abs(gear_ratio - 1.0) < 1e-9 else ChainKind.BELT


def layout_for(spec: ModelSpec, conditions: int) -> Layout:
    """Parameter blocks of a model; effect blocks start at zero (the nominal model)."""
    lay = Layout()
    lay.add(Block("delay_ms", 1, 0.5, -3.0, 5.0))
    lay.add(Block("angle_offset_rad", 1, 0.0, -0.5, 0.5))
    lay.add(Block("load_angle_rad", conditions, 0.0, -1.3, 1.3))
    lay.add(Block("amp_offset_mA", 2, 0.0, -2000.0, 2000.0))
    lay.add(Block("amp_gain_error", 2, 0.0, -0.45, 0.45))
    lay.add(Block("rotor_hz_at_1A", 1, 120.0, 3.0, 5000.0))
    lay.add(Block("rotor_damping_per_s", 1, 50.0, 0.0, 5000.0))
    if spec.chain is ChainKind.BELT:
        lay.add(Block("load_inertia_ratio", 1, 10.0, 0.01, 1e4))
        lay.add(Block("belt_hz", 1, 20.0, 0.5, 2000.0))
        lay.add(Block("belt_damping_ratio", 1, 0.05, 0.0, 2.0))
    if Effect.LOAD_RESONANCE in spec.effects:
        lay.add(Block("coupling_inertia_fraction", 1, 0.5, 0.02, 0.98))
        lay.add(Block("coupling_hz", 1, 150.0, 5.0, 3000.0))
        lay.add(Block("coupling_damping_ratio", 1, 0.05, 0.0, 1.0))
    if Effect.FLUX_HARMONICS in spec.effects:
        lay.add(Block("flux", 4 * len(FLUX_ORDERS), 0.0))
    if Effect.CURRENT_DISTORTION in spec.effects:
        lay.add(Block("distortion", 4 * len(DISTORTION_ORDERS), 0.0))
    if Effect.DETENT_TORQUE in spec.effects:
        lay.add(Block("detent", 2 * len(DETENT_ORDERS), 0.0))
    if Effect.RELUCTANCE_TORQUE in spec.effects:
        lay.add(Block("reluctance", 1, 0.0))
    return lay


@dataclass(frozen=True)
class _Stage:
    """One inertia of the chain (μ = J/Kt, γ = c/Kt) and the spring to the next one."""

    inertia: float
    damping: float
    spring: float = 0.0  # κ = k/Kt of the spring to the next inertia (0: last inertia)
    spring_damping: float = 0.0
    ratio: float = 1.0  # next angle per this angle through the spring


@dataclass(frozen=True)
class _Motion:
    """What the error and its linear design are both built on, for one parameter set."""

    a: NDArray[np.complex128]  # load angular acceleration per order (table's frame)
    torque_per_a: NDArray[np.complex128]  # torque the chain needs per unit of ``a``
    te: NDArray[np.float64]  # rotor electrical angle on the grid
    i_a: NDArray[np.float64]
    i_b: NDArray[np.float64]
    sensitivity: NDArray[np.complex128]  # d(error)/d(a)


class Model:
    """A model (nominal, or nominal plus effect groups) bound to one set of observations."""

    def __init__(self, spec: ModelSpec, obs: Observations) -> None:
        self.spec = spec
        self.obs = obs
        self.layout = layout_for(spec, len(obs.conditions))
        meta = obs.metadata
        self.rotor_teeth = meta.rotor_teeth
        self.radius = meta.sensor_radius_m
        self.gear_ratio = meta.gear_ratio
        k = np.arange(1, obs.orders + 1, dtype=np.float64)
        self.k = k
        x = 2.0 * np.pi * np.arange(GRID) / GRID
        self.x = x
        self.synth = np.exp(1j * np.outer(k, x))  # (K, N): order k at grid point n
        self.analyse = 2.0 / GRID * np.exp(-1j * np.outer(x, k))  # (N, K)
        self.s = 1j * obs.omega[:, None] * k[None, :]  # (S, K): d/dt of order k
        # σ is the spread of the complex phasor; each of its two parts carries half.
        self.weight = math.sqrt(2.0) / np.maximum(obs.sigma, 1e-12)
        trims = obs.trims
        amp = obs.amplitude_A[:, None]
        self.trim_offset_A = trims[:, :2] * 1e-3
        self.trim_gain = trims[:, 2:] / GAIN_UNITY
        self.cos_x = np.cos(x)[None, :]
        self.sin_x = np.sin(x)[None, :]
        self.amp = amp
        # Harmonic waveforms of the currents, per distortion order (unscaled).
        self._dist_waves = [
            (np.cos(h * x), np.sin(h * x), np.cos(h * (x - QUARTER)), np.sin(h * (x - QUARTER)))
            for h in DISTORTION_ORDERS
        ]

    # ------------------------------------------------------------------ pieces
    def _chain(self, p: NDArray[np.float64]) -> list[_Stage]:
        sl = self.layout.slices
        nr = self.rotor_teeth
        w1 = 2.0 * math.pi * p[sl["rotor_hz_at_1A"]][0]
        inertia = nr / (w1 * w1)  # μ with rotor (and rigidly attached mass) on Nr·I at 1 A
        damping = p[sl["rotor_damping_per_s"]][0] * inertia
        resonant = Effect.LOAD_RESONANCE in self.spec.effects
        if resonant:
            frac = p[sl["coupling_inertia_fraction"]][0]
            wc = 2.0 * math.pi * p[sl["coupling_hz"]][0]
            zc = p[sl["coupling_damping_ratio"]][0]
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
        mu_l = p[sl["load_inertia_ratio"]][0] * inertia / (n * n)
        wb = 2.0 * math.pi * p[sl["belt_hz"]][0]
        kb = mu_l * wb * wb
        cb = 2 * p[sl["belt_damping_ratio"]][0] * math.sqrt(kb * mu_l)
        load = _Stage(mu_l, 0.0)
        if not resonant:
            return [_Stage(inertia, damping, kb, cb, n), load]
        mu_p = frac * inertia
        kappa = mu_p * wc * wc
        return [
            _Stage((1 - frac) * inertia, damping, kappa, 2 * zc * math.sqrt(kappa * mu_p)),
            _Stage(mu_p, 0.0, kb, cb, n),
            load,
        ]

    def _transfer(
        self, stages: Sequence[_Stage]
    ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """Rotor angle and required motor torque per unit load angular acceleration, (S, K)."""
        s = self.s
        last = stages[-1]
        theta = np.asarray(1.0 / (s * s), dtype=np.complex128)
        torque = np.asarray(last.inertia + last.damping / s, dtype=np.complex128)
        for st in reversed(stages[:-1]):
            twist = torque / (st.spring + s * st.spring_damping)
            theta = np.asarray((theta + twist) / st.ratio, dtype=np.complex128)
            torque = np.asarray(
                (st.inertia * s * s + st.damping * s) * theta + st.ratio * torque,
                dtype=np.complex128,
            )
        return theta, torque

    def _currents(
        self, p: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
        """Phase currents (A) on the grid of every segment, and the fundamental's amplitude."""
        sl = self.layout.slices
        amp_off = p[sl["amp_offset_mA"]] * 1e-3
        gain = (1.0 + p[sl["amp_gain_error"]])[None, :] * self.trim_gain  # (S, 2)
        ga = gain[:, :1] * self.amp
        gb = gain[:, 1:] * self.amp
        wave_a = np.broadcast_to(self.cos_x, (self.obs.count, GRID)).copy()
        wave_b = np.broadcast_to(self.sin_x, (self.obs.count, GRID)).copy()
        if "distortion" in sl:
            c = p[sl["distortion"]]
            for i, (ca, sa, cb, sb) in enumerate(self._dist_waves):
                wave_a += c[4 * i] * ca + c[4 * i + 1] * sa
                wave_b += c[4 * i + 2] * cb + c[4 * i + 3] * sb
        i_a = (self.trim_offset_A[:, :1] + amp_off[0]) + ga * wave_a
        i_b = (self.trim_offset_A[:, 1:] + amp_off[1]) + gb * wave_b
        return i_a, i_b, 0.5 * (ga + gb)[:, 0]

    def _torque(
        self, p: NDArray[np.float64], te: NDArray[np.float64], i_a: NDArray[np.float64],
        i_b: NDArray[np.float64],
    ) -> NDArray[np.float64]:
        """Eq. (1) in units of Kt: the magnet torque plus whatever effect groups are on."""
        sl = self.layout.slices
        s1 = np.sin(te)
        c1 = np.cos(te)
        u = i_b * c1 - i_a * s1
        if "flux" in sl:
            c = p[sl["flux"]]
            for i, j in enumerate(FLUX_ORDERS):
                ta = j * te
                tb = j * (te - QUARTER)
                u -= j * i_a * (c[4 * i] * np.sin(ta) + c[4 * i + 1] * np.cos(ta))
                u -= j * i_b * (c[4 * i + 2] * np.sin(tb) + c[4 * i + 3] * np.cos(tb))
        if "detent" in sl:
            c = p[sl["detent"]]
            for i, d in enumerate(DETENT_ORDERS):
                u += c[2 * i] * np.sin(d * te) + c[2 * i + 1] * np.cos(d * te)
        if "reluctance" in sl:
            lam = p[sl["reluctance"]][0]
            c2 = c1 * c1 - s1 * s1
            s2 = 2.0 * s1 * c1
            u += lam * (2.0 * c2 * i_a * i_b - s2 * (i_a * i_a - i_b * i_b))
        return u

    def _rotation(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        """Per order, what takes a measured phasor into the current table's angle frame:
        the sensor's delay undone and the table's angle offset applied, (S, K)."""
        sl = self.layout.slices
        delay = p[sl["delay_ms"]][0] * 1e-3
        psi = p[sl["angle_offset_rad"]][0]
        out: NDArray[np.complex128] = np.exp(
            1j * self.k[None, :] * (self.obs.omega[:, None] * delay - psi)
        )
        return out

    def _motion(self, p: NDArray[np.float64]) -> _Motion:
        """The measured motion carried back to the rotor, and the currents driving it."""
        a = self.obs.phasors * self._rotation(p) / self.radius
        theta, torque_per_a = self._transfer(self._chain(p))
        ripple = ((theta * a) @ self.synth).real  # rotor angle ripple on the grid (mech. rad)
        rho = p[self.layout.slices["load_angle_rad"]][self.obs.condition]
        te = self.x[None, :] - rho[:, None] + self.rotor_teeth * ripple
        i_a, i_b, i_fund = self._currents(p)
        # d(error)/d(a): the magnet's spring acting on the rotor's swing, minus the chain.
        stiffness = -(i_fund * np.cos(rho))[:, None] * self.rotor_teeth
        return _Motion(a, torque_per_a, te, i_a, i_b, stiffness * theta - torque_per_a)

    def _error(self, p: NDArray[np.float64], m: _Motion) -> NDArray[np.complex128]:
        """Torque the model makes minus torque the motion needs, per order, (S, K)."""
        made = self._torque(p, m.te, m.i_a, m.i_b) @ self.analyse
        out: NDArray[np.complex128] = made - m.torque_per_a * m.a
        return out

    # ------------------------------------------------------------------ linear part
    def linear_blocks(self) -> list[str]:
        """Blocks the equation error depends on (almost) linearly: solved, not searched."""
        return [b.name for b in self.layout.blocks if b.name in LINEAR_BLOCKS]

    def linear_index(self) -> NDArray[np.intp]:
        sl = self.layout.slices
        return np.concatenate([np.arange(sl[n].start, sl[n].stop) for n in self.linear_blocks()])

    def linear_design(
        self, p: NDArray[np.float64]
    ) -> tuple[NDArray[np.complex128], NDArray[np.complex128]]:
        """(error at zero linear parameters, d error / d linear parameter), in weighted m/s².

        Exact in the amplifier offsets, detent and the fundamental's gain errors;
        the flux, distortion and reluctance bases use the current iterate's
        currents, so a couple of passes settle their small cross terms.
        """
        sl = self.layout.slices
        m = self._motion(p)
        te, i_a, i_b = m.te, m.i_a, m.i_b
        s1, c1 = np.sin(te), np.cos(te)
        ga = self.trim_gain[:, :1] * self.amp
        gb = self.trim_gain[:, 1:] * self.amp
        bases: list[NDArray[np.float64]] = []
        for name in self.linear_blocks():
            if name == "amp_offset_mA":
                bases += [-1e-3 * s1, 1e-3 * c1]
            elif name == "amp_gain_error":
                off = self.trim_offset_A + p[sl["amp_offset_mA"]][None, :] * 1e-3
                gain = 1.0 + p[sl["amp_gain_error"]]
                # ∂i/∂e is the phase's nominal waveform, distortion included.
                bases += [-(i_a - off[:, :1]) / gain[0] * s1, (i_b - off[:, 1:]) / gain[1] * c1]
            elif name == "flux":
                for j in FLUX_ORDERS:
                    ta, tb = j * te, j * (te - QUARTER)
                    bases += [-j * i_a * np.sin(ta), -j * i_a * np.cos(ta),
                              -j * i_b * np.sin(tb), -j * i_b * np.cos(tb)]
            elif name == "distortion":
                gain = (1.0 + p[sl["amp_gain_error"]])
                for ca, sa, cb, sb in self._dist_waves:
                    bases += [-gain[0] * ga * ca * s1, -gain[0] * ga * sa * s1,
                              gain[1] * gb * cb * c1, gain[1] * gb * sb * c1]
            elif name == "detent":
                for d in DETENT_ORDERS:
                    bases += [np.sin(d * te), np.cos(d * te)]
            elif name == "reluctance":
                bases.append(2.0 * np.cos(2 * te) * i_a * i_b - np.sin(2 * te) * (i_a**2 - i_b**2))
        design = np.stack(bases) @ self.analyse  # (L, S, K)
        scale = self.radius / m.sensitivity * self.weight
        beta = p[self.linear_index()]
        at_zero = self._error(p, m) - np.tensordot(beta, design, axes=1)
        return at_zero * scale, design * scale[None, :, :]

    # ------------------------------------------------------------------ residuals
    def equation_error(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The error as sensor acceleration (m/s²) per segment and order, (S, K)."""
        m = self._motion(p)
        out: NDArray[np.complex128] = self._error(p, m) / m.sensitivity * self.radius
        return out

    def residuals(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Weighted residuals (real and imaginary parts) for a least-squares solver."""
        z = self.equation_error(p) * self.weight
        return np.concatenate([z.real.ravel(), z.imag.ravel()])

    def predicted(self, p: NDArray[np.float64]) -> NDArray[np.complex128]:
        """The harmonics this model says the sensor should have measured (m/s²), (S, K)."""
        out: NDArray[np.complex128] = self.obs.phasors - self.equation_error(p) / self._rotation(p)
        return out

    def in_mps2(self, weighted: NDArray[np.float64]) -> NDArray[np.float64]:
        """Weighted residuals (as ``residuals`` lays them out) back in m/s², shape (2, S, K):
        real and imaginary parts of each segment's and order's residual."""
        shaped = weighted.reshape(2, self.obs.count, self.obs.orders)
        out: NDArray[np.float64] = shaped / self.weight
        return out

    def residual_rows(self) -> NDArray[np.intp]:
        """Segment index of every entry of ``residuals`` (for holding out conditions)."""
        seg = np.repeat(np.arange(self.obs.count), self.obs.orders)
        return np.concatenate([seg, seg])
