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
CLI.md's vocabulary, each its own module (``station.diagnosis.effects``); each
adds a few parameters to this one model and acts on it through hook points
(``station.diagnosis.hooks``: the currents, the torque, the chain, the load,
the sensor), so any combination of them is a model too, and the model never
asks which it holds.
"""

from __future__ import annotations

import math
from functools import cached_property, reduce
from typing import Any, TypeVar

import numpy as np
from numpy.typing import NDArray

from station.core import GAIN_UNITY
from station.diagnosis import axes, balance, chain, effects, jacobian
from station.diagnosis.effects import friction
from station.diagnosis.hooks import Hooks, Role
from station.diagnosis.layout import Block, BlockKind, ChainKind, Layout, ModelSpec
from station.diagnosis.motion import (
    COMMON_GAIN_SIGMA,
    Chain,
    Inputs,
    Linearised,
    Memo,
    Motion,
    Step,
    flatten,
    real_map,
    stacked,
)
from station.diagnosis.observations import Observations, bend_bases, radial_ripple

GRID = 48
"""Points per electrical period where torques are evaluated: orders up to 23 alias-free,
and an order must reach 40 to fold onto the 8 analysed. The swing's orders reach 16, so
products of a few of them fit; measured on seven recordings' fitted models (cogging
several times the magnet torque among them), every residual moved by under 1e-5 σ
from a 64-point grid, for a quarter less of every evaluation's grid work."""

NEAR_REFINE = 4
NEAR_START = 1e-3
NEAR_DONE = 1e-14
"""Newton–Schulz passes at most, the error of the start beyond which the matrix is
inverted afresh instead, and the error at which refining stops (``Model.step``):
a difference step leaves an error near 1e-6, gone to rounding after two passes."""
FINE_OVERSAMPLE = 4
"""How much finer than the grid the current role's finer grid is (``Model.fine_synth``):
a bridge's dead time forms its turns there before they are cut to the grid's orders."""

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


SENSOR_KEYS = ("sensor_a1_ms", "sensor_a2_ms2")
"""What the sensor's response is made of (``Model.sensor_response``), beside what its
effects' hooks read (``Hooks.reads``: so for every ``*_KEYS``)."""
MEASURED_KEYS = ("axis_mix", "sensor_bend")
"""What the measured tangential motion is corrected with (``Model.measured``)."""
CURRENT_KEYS = ("amp_offset_mA", "amp_gain_error")
"""What the currents the drive made are made of (``Model.current_coefficients``)."""
CHAIN_KEYS = ("log_rotor_hz", "rotor_damping_ratio", "log_load_ratio", "log_belt_hz",
              "belt_damping_ratio", "load_damping_ratio")
"""What the chain's inertias, springs and dampers are made of (``chain.stages_at``)."""
FRICTION_KEYS = ("friction_coulomb", "log_friction_smoothing")
"""What the load's friction is made of, beside the load's motion (``friction.friction_torque``)."""

NOMINAL_KEYS = {Role.CURRENTS: CURRENT_KEYS, Role.CHAIN: CHAIN_KEYS, Role.SENSOR: SENSOR_KEYS}
"""What each role reads of the nominal model's own blocks."""

_T = TypeVar("_T")





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
        # Each effect's hooks, in the layout's order of the effects.
        self.hooks: list[Hooks] = [effects.terms(e).hooks for e in sorted(spec.effects)]
        # Current harmonics on the grid: order 1 (the table), then the effects' own.
        self.current_orders = np.array([1, *(h for hooks in self.hooks
                                             for h in hooks.current_orders)], dtype=np.float64)
        self.current_synth = np.exp(1j * np.outer(self.current_orders, x))  # (H, N)
        self.load_speed = obs.load_speed[:, None]  # rad/s at the load
        self.bend = bend_bases(obs) if spec.sensor_bend else None
        self.radial = radial_ripple(obs) if obs.axis_mixed else None
        self._last: tuple[NDArray[np.float64], Motion] | None = None
        sensor = (*self.keys(Role.SENSOR), *MEASURED_KEYS)
        self._sensor: Memo[NDArray[np.complex128]] = self._memo(self.keys(Role.SENSOR))
        self._sensor_beyond: Memo[NDArray[np.complex128]] = self._memo(
            self.keys(Role.SENSOR))
        self._alpha: Memo[tuple[NDArray[np.complex128], NDArray[np.complex128],
                                 NDArray[np.complex128] | None]] = self._memo(sensor)
        self._friction: Memo[tuple[NDArray[np.complex128], NDArray[np.float64],
                                    NDArray[np.float64]]] = self._memo((*sensor, *FRICTION_KEYS))
        # Friction's shapes do not move with its levels: a Jacobian's columns of the levels
        # would otherwise make them again, most of a friction model's evaluation.
        self._friction_shapes: Memo[tuple[NDArray[np.float64], ...]] = self._memo(
            (*sensor, "log_friction_smoothing"))
        self._chain: Memo[Chain] = self._memo(self.keys(Role.CHAIN))
        self._coefficients: Memo[tuple[NDArray[np.float64], NDArray[np.complex128],
                                        NDArray[np.float64], NDArray[np.complex128]]] = (
            self._memo(self.keys(Role.CURRENTS)))
        self._currents: Memo[tuple[NDArray[np.float64], NDArray[np.float64]]] = self._memo(
            self.keys(Role.CURRENTS))
        self._residuals: Memo[NDArray[np.float64]] = Memo(np.arange(self.layout.size))
        self._pieces: dict[str, Memo[Any]] = {}
        self._linear_memo: Memo[Linearised] = Memo(np.arange(self.layout.size))
        self.torque_index = self._memo(self.keys(Role.TORQUE)).index
        # The torque made and the error's step on the motion at p: the residuals and the
        # linear design (both asked for at each Jacobian's point) share them.
        self._made: Memo[tuple[NDArray[np.float64], Step]] = Memo(
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

    def keys(self, role: Role) -> tuple[str, ...]:
        """The blocks a role's pieces are made of: the nominal's and its effects' hooks'."""
        own = NOMINAL_KEYS.get(role, ())
        return (*own, *(name for hooks in self.hooks for name in hooks.reads.get(role, ())))

    def each(self, point: str) -> list[Any]:
        """The effects' hooks at one of ``Hooks``'s points, in the effects' order."""
        return [getattr(h, point) for h in self.hooks if getattr(h, point) is not None]

    def current_column(self, order: int) -> int:
        """Where a harmonic of the currents sits in ``current_orders``."""
        return int(np.flatnonzero(self.current_orders == order)[0])

    @cached_property
    def fine_synth(self) -> NDArray[np.complex128]:
        """The current harmonics on a grid ``FINE_OVERSAMPLE`` times finer, (H, N·F)."""
        n = FINE_OVERSAMPLE * GRID
        out: NDArray[np.complex128] = np.exp(
            1j * np.outer(self.current_orders, 2.0 * np.pi * np.arange(n) / n))
        return out

    def kept(self, piece: str, role: Role) -> Memo[Any]:
        """A memo for an effect's own piece of the model, keyed on what ``role`` reads: a
        hook that needs the same piece twice at a point (a dead time's currents before
        it, for the currents and for their bases) makes it once."""
        memo = self._pieces.get(piece)
        if memo is None:
            memo = self._pieces[piece] = self._memo(self.keys(role))
        return memo

    def _memo(self, names: tuple[str, ...]) -> Memo[_T]:
        """A memo keyed on the named blocks this model has."""
        every = np.arange(self.layout.size)
        parts = [every[self.layout.slices[n]] for n in names if self.layout.has(n)]
        return Memo(np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp))

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
        """Where the chain's parameters sit (``CHAIN_KEYS``): what ``chain.stages_at`` reads."""
        return self._chain.index

    def block(self, p: NDArray[np.float64], name: str) -> NDArray[np.float64]:
        """The named block's values in ``p``."""
        return p[self.layout.slices[name]]

    def scalar(self, p: NDArray[np.float64], name: str) -> float:
        return float(p[self.layout.slices[name]][0])

    def sensor_response(self, p: NDArray[np.float64], beyond: bool = False
                        ) -> NDArray[np.complex128]:
        """What the sensor (its low-pass, its clock) makes of each order, (S, K); of the
        orders above the modelled ones with ``beyond``."""
        memo = self._sensor_beyond if beyond else self._sensor
        return memo.get(p, lambda: self._sensor_response(p, beyond))

    def _sensor_response(self, p: NDArray[np.float64], beyond: bool
                         ) -> NDArray[np.complex128]:
        a1 = self.scalar(p, "sensor_a1_ms") * 1e-3
        a2 = self.scalar(p, "sensor_a2_ms2") * 1e-6
        s, k = (self.jw_beyond, self.k_beyond) if beyond else (self.jw, self.k)
        out: NDArray[np.complex128] = 1.0 / (1.0 + a1 * s + a2 * s * s)
        for hook in self.each("sensor"):
            out = out * hook(self, p, k)
        return out

    def current_response(self, p: NDArray[np.float64]) -> tuple[NDArray[np.complex128],
                                                                NDArray[np.complex128]]:
        """Each phase's response at each current harmonic, (S, H) each: 1 unless an
        effect's loop stands between command and current."""
        one = np.ones((self.obs.count, self.current_orders.size), dtype=np.complex128)
        out_a, out_b = one, one
        for hook in self.each("current_response"):
            out_a, out_b = hook(self, p, out_a, out_b)
        return out_a, out_b

    def current_coefficients(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64],
            NDArray[np.complex128]]:
        """Each phase as DC plus harmonics: (DC (S, 1), harmonics (S, H)) for A and B."""
        return self._coefficients.get(p, lambda: self._current_coefficients(p))

    def _current_coefficients(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.float64], NDArray[np.complex128], NDArray[np.float64],
            NDArray[np.complex128]]:
        amp_off = self.block(p, "amp_offset_mA") * 1e-3
        gain = (1.0 + self.block(p, "amp_gain_error"))[None, :] * self.trim_gain  # (S, 2)
        ga = gain[:, :1] * self.amp
        gb = gain[:, 1:] * self.amp
        lag_a, lag_b = self.current_response(p)
        wave_a = np.zeros((self.obs.count, self.current_orders.size), dtype=np.complex128)
        wave_b = np.zeros_like(wave_a)
        wave_a[:, 0] = 1.0  # cos x
        wave_b[:, 0] = -1j  # sin x
        column = 1
        for hooks in self.hooks:
            orders = len(hooks.current_orders)
            if hooks.current_wave is not None:
                own = slice(column, column + orders)
                wave_a[:, own], wave_b[:, own] = hooks.current_wave(self, p)
            column += orders
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
        for hook in self.each("current_made"):
            i_a, i_b = hook(self, p, i_a, i_b)
        return i_a, i_b

    def band_limited(self, fine: NDArray[np.float64]) -> NDArray[np.float64]:
        """A periodic waveform formed on the finer grid (``fine_synth``), cut to the orders
        the grid holds and sampled on it: a sign's harmonics fall only as 1/k, and sampled
        on the grid itself they would fold back onto the low orders."""
        spectrum = np.fft.rfft(fine, axis=-1)[..., :GRID // 2]
        out: NDArray[np.float64] = np.fft.irfft(spectrum, n=GRID, axis=-1) * (
            GRID / fine.shape[-1])
        return out

    def modulation(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The factor on the magnet's and the cogging torque per segment, (S, 1): 1 unless
        an effect modulates it (an eccentric airgap, once per revolution)."""
        hooks = self.each("modulation")
        if not hooks:
            return np.ones((self.obs.count, 1))
        out: NDArray[np.float64] = reduce(lambda a, b: a * b, (h(self, p) for h in hooks))
        return out

    def unbalance(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """The mean loads on the rotor the effects put beside the chain's own drag (Kt
        units, (S,)): within one electrical period a constant load, which moves the rotor
        along its magnetic spring and with it every harmonic's phase."""
        hooks = self.each("load")
        if not hooks:
            return np.zeros(self.obs.count)
        out: NDArray[np.float64] = reduce(lambda a, b: a + b, (h(self, p) for h in hooks))
        return out

    def kt_factor(self, p: NDArray[np.float64], i_a: NDArray[np.float64],
                  i_b: NDArray[np.float64]) -> NDArray[np.float64] | float:
        """Kt relative to its low-current value at the instantaneous currents."""
        out: NDArray[np.float64] | float = 1.0
        for hook in self.each("kt"):
            out = out * hook(self, p, i_a, i_b)
        return out

    def kt_slopes(self, p: NDArray[np.float64], m: Motion
                  ) -> tuple[NDArray[np.float64] | float, NDArray[np.float64] | float]:
        """∂(Kt factor)/∂i_A and ∂/∂i_B, by the product rule over the effects' factors."""
        pairs = [(h.kt, h.kt_slope) for h in self.hooks if h.kt is not None]
        factors = [kt(self, p, m.i_a, m.i_b) for kt, _ in pairs]
        d_a: NDArray[np.float64] | float = 0.0
        d_b: NDArray[np.float64] | float = 0.0
        for i, (_, slope) in enumerate(pairs):
            assert slope is not None, "a Kt factor without its slope"
            g_a, g_b = slope(self, p, m)
            others = [f for j, f in enumerate(factors) if j != i]
            rest = reduce(lambda a, b: a * b, others) if others else None
            d_a = d_a + (g_a if rest is None else g_a * rest)
            d_b = d_b + (g_b if rest is None else g_b * rest)
        return d_a, d_b

    def magnet_weights(self, p: NDArray[np.float64], m: Motion
                       ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """∂(magnet torque)/∂i_A and ∂/∂i_B on the grid: −sin θe, cos θe and the effects'."""
        pa = -m.sin_te
        pb = m.cos_te
        for hook in self.each("magnet"):
            pa, pb = hook(self, p, m, pa, pb)
        return pa, pb

    def inner_torque(self, p: NDArray[np.float64], m: Motion, magnet: NDArray[np.float64]
                     ) -> NDArray[np.float64]:
        """kt·magnet + cogging: the torque the modulation multiplies."""
        made = self.kt_factor(p, m.i_a, m.i_b) * magnet
        for hook in self.each("cogging"):
            made = hook(self, p, m, made)
        out: NDArray[np.float64] = made
        return out

    def torque(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """Eq. (1) in units of Kt on the grid: τ = mod·(kt·magnet + cogging) + beside, each
        part as the effects' hooks make it (``station.diagnosis.hooks``)."""
        pa, pb = self.magnet_weights(p, m)
        magnet = m.i_a * pa + m.i_b * pb
        made = self.inner_torque(p, m, magnet) * m.modulation
        for hook in self.each("beside"):
            made = hook(self, p, m, made)
        return made

    def friction_shapes_here(self, p: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
        """``friction_shapes`` on the load's velocity at ``p`` (kept: the torque and the
        linear design both ask for it at the same point)."""
        return self._friction_shapes.get(
            p, lambda: friction.friction_shapes(self, p, friction.load_velocity(self, p)))

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

    def load_motion(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128], NDArray[np.complex128] | None]:
        """``_load_motion`` at ``p``, kept (the sensor's and the measurement's pieces)."""
        return self._alpha.get(p, lambda: self._load_motion(p))

    def _load_motion(self, p: NDArray[np.float64]) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128], NDArray[np.complex128] | None]:
        """The sensor's response, and the load's acceleration per order it says the
        measurement was, below and above the modelled orders."""
        sensor = self.sensor_response(p)
        below, beyond = axes.measured(self, p)
        alpha = below / (sensor * self.radius)
        above = (None if beyond is None
                 else beyond / (self.sensor_response(p, beyond=True) * self.radius))
        return sensor, alpha, above

    def _motion(self, p: NDArray[np.float64]) -> Motion:
        x = self.inputs(p)
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
        return first.shifted(balance.trim_lag(self, p, first))

    def inputs(self, p: NDArray[np.float64], made: Chain | None = None) -> Inputs:
        """The motion's inputs at ``p``, its chain ``made`` already if given
        (``chain.chains``)."""
        sensor, alpha, above = self.load_motion(p)
        transfer, theta_above, drag = (self._chain.get(p, lambda: chain.chain_at(self, p))
                                       if made is None else made)
        force, slope, mean_force = self._friction.get(
            p, lambda: friction.friction_torque(self, p))
        unbalance = self.unbalance(p)
        taken = drag + unbalance + self.gear_ratio * mean_force
        swing_above = None if above is None or theta_above is None else theta_above * above
        i_a, i_b = self.currents(p)
        return Inputs(sensor, alpha, transfer, swing_above, force, slope, taken,
                       self.block(p, "load_angle_rad")[self.obs.condition], i_a, i_b,
                       self.modulation(p), unbalance)

    def torque_slope(self, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
        """∂(torque made)/∂θe on the grid, every term included: the magnetic spring."""
        da = -m.cos_te
        db = -m.sin_te
        for hook in self.each("magnet_slope"):
            da, db = hook(self, p, m, da, db)
        slope = self.kt_factor(p, m.i_a, m.i_b) * (m.i_a * da + m.i_b * db)
        for hook in self.each("cogging_slope"):
            slope = hook(self, p, m, slope)
        slope = slope * m.modulation
        for hook in self.each("beside_slope"):
            slope = hook(self, p, m, slope)
        out: NDArray[np.float64] = slope
        return out

    def rotor_response(self, m: Motion, x: NDArray[np.complex128]) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128]]:
        """The rotor angle's and the needed torque's change for a change ``x`` of the
        load's acceleration (S, K), friction moving with the load's velocity."""
        t = m.transfer
        force = friction.friction_response(self, m.friction_slope, x)
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
        spring = real_map(self.rotor_teeth * both[:, 0], self.rotor_teeth * both[:, 1])
        return np.asarray(spring @ stacked(theta) - stacked(need), dtype=np.float64)

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

    def linear_design(self, p: NDArray[np.float64]
                      ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """(weighted residuals at zero linear parameters, d residuals / d linear
        parameter, (L, n)), laid out as ``residuals``.

        Each segment's slip and the error's scale are held where ``p`` leaves them
        (``linear_jacobian`` moves them too), and the bases of products (flux,
        distortion, saturation, reluctance with the currents) use the current iterate:
        a couple of passes settle what that leaves.
        """
        return jacobian.design_and_bases(self, p)[:2]

    def linear_jacobian(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """d residuals / d linear parameter, (n, L) (``jacobian.linear_jacobian``)."""
        return jacobian.linear_jacobian(self, p)

    def motion_columns(self, p: NDArray[np.float64], points: list[NDArray[np.float64]],
                       steps: NDArray[np.float64]) -> NDArray[np.float64]:
        """d residuals / d the parameters that enter only the motion's inputs, each given
        as ``p`` moved by its step (``jacobian.motion_columns``)."""
        return jacobian.motion_columns(self, p, points, steps)

    def linearised(self, p: NDArray[np.float64]) -> Linearised:
        """What every analytic Jacobian column at ``p`` shares, kept."""
        return self._linear_memo.get(p, lambda: jacobian.linearise(self, p))

    def motion_index(self) -> NDArray[np.intp]:
        """Parameters whose Jacobian columns come through the motion's inputs
        (``motion_columns``): the nonlinear ones, and the friction levels, which move the
        load's swing and with it every rotor angle of the grid."""
        out = [self.layout.indices(BlockKind.NONLINEAR),
               np.arange(self.layout.size)[self.layout.slices["friction_coulomb"]]]
        return np.sort(np.concatenate(out))

    def linear_names(self) -> list[str]:
        return [b.name for b in self.layout.blocks if b.kind is BlockKind.LINEAR
                for _ in range(b.size)]

    def prior(self, p: NDArray[np.float64]) -> NDArray[np.float64]:
        """What the drive's datasheet says without the recording: its current amplitude is
        calibrated to a few percent. Only the gains' mean is held to that (their split is
        what the recording measures): alone it is weakly identified (it trades against
        the rotor's frequency), and a fit would wander along that valley."""
        common = float(np.mean(self.block(p, "amp_gain_error")))
        return np.array([common / COMMON_GAIN_SIGMA])

    # ------------------------------------------------------------------ the DC balance
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
        dc = balance.dc_error(self, p, m, made) * balance.dc_weight(self)
        return flatten(step.apply(self.error(p, m, made)), dc, self.prior(p))

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

    # ------------------------------------------------------------------ physics out
