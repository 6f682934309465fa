"""The simulated bench's physics: drive currents, motor torque, load chain, sensor.

The plant advances one SYNC period at a time, because that is the granularity
at which the drive changes its inputs and the sensor reports (ICD.md §1). Inside
a period it integrates the nonlinear model at a fixed step with semi-implicit
(symplectic) Euler: trim sweeps swing the rotor far enough that a linearised
model would lie, and a fixed step keeps runs reproducible bit for bit.

The inner loop is scalar code on purpose (per-step numpy calls cost
microseconds each), compiled by numba in ``kernel``; everything that can be
is precomputed in ``__init__``, and this class keeps what happens once per
SYNC: commands, the sensor's sampling and its counts.
"""

from __future__ import annotations

import cmath
import hashlib
import math
from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.linalg import expm

from station.core import (
    GAIN_LIMITS,
    GAIN_UNITY,
    SATURATED_COUNTS,
    SENSOR_RANGES_G,
    STANDARD_GRAVITY,
    Axis,
    Trims,
)
from station.physics import kernel as k_
from station.physics.kernel import TABLE_SIZE
from station.physics.motor import (
    QUARTER_PITCH_ELECTRICAL,
    MotorParams,
    magnetic_stiffness,
    rest_angle,
)
from station.physics.params import (
    AmplifierParams,
    FrictionParams,
    UnitParams,
)

_NOISE_BLOCK = 4096


@dataclass(frozen=True, slots=True)
class DriveCommand:
    """What the drive imposes during one SYNC period (piecewise constant inputs).

    Built once per SYNC by the simulated drive, so it is kept light: the
    plant checks it when it is used.
    """

    enabled: bool
    amplitude_mA: float
    trims: Trims
    position_start: float
    velocity: float
    acceleration: float
    microsteps_per_fullstep: int


STAIRCASE_LAG_MICROSTEPS = 0.5
"""The drive's current staircase follows the integer position demand: on
average half a microstep behind the ramp it is cut from."""


def commanded_currents_A(x_u: ArrayLike, amplitude_mA: float, trims: Trims,
                         amplifier: AmplifierParams) -> tuple[NDArray[np.float64],
                                                              NDArray[np.float64]]:
    """Steady phase currents (A) at electrical angle x_u: ICD.md §2 plus the amplifier.

    i_A = off_trim + off_amp + (1 + e_A)·(g_A/10000)·I·[cos x_u + distortion],
    phase B likewise on sin x_u = cos(x_u − π/2), less a dead time's error if the
    amplifier has one. The current loop's lag is a
    dynamic effect and is left to the plant.
    """
    x = np.asarray(x_u, dtype=np.float64)
    amp = amplitude_mA * 1e-3
    fa = (1.0 + amplifier.gain_error_a) * trims.gain_a / GAIN_UNITY * amp
    fb = (1.0 + amplifier.gain_error_b) * trims.gain_b / GAIN_UNITY * amp
    wave_a = np.cos(x)
    wave_b = np.sin(x)
    for h in amplifier.distortion_a:
        wave_a = wave_a + h.relative * np.cos(h.order * x + h.phase_rad)
    for h in amplifier.distortion_b:
        shifted = h.order * (x - QUARTER_PITCH_ELECTRICAL) + h.phase_rad
        wave_b = wave_b + h.relative * np.cos(shifted)
    i_a = (trims.offset_a_mA + amplifier.offset_a_mA) * 1e-3 + fa * wave_a
    i_b = (trims.offset_b_mA + amplifier.offset_b_mA) * 1e-3 + fb * wave_b
    if amplifier.dead_time_mA > 0.0:
        dead, knee = amplifier.dead_time_mA * 1e-3, amplifier.dead_time_knee_mA * 1e-3
        i_a = i_a - dead * np.tanh(i_a / knee)
        i_b = i_b - dead * np.tanh(i_b / knee)
    return np.asarray(i_a, dtype=np.float64), np.asarray(i_b, dtype=np.float64)


@dataclass(frozen=True)
class LumpedFriction:
    """Friction on one inertia, all sources summed (the smallest smoothing wins)."""

    viscous: float
    coulomb_pos: float
    coulomb_neg: float
    smoothing: float

    @staticmethod
    def combine(sources: list[FrictionParams | None]) -> LumpedFriction:
        present = [s for s in sources if s is not None]
        if not present:
            return LumpedFriction(0.0, 0.0, 0.0, 1.0)
        return LumpedFriction(
            sum(s.viscous_Nms for s in present),
            sum(s.coulomb_pos_Nm for s in present),
            sum(s.coulomb_neg_Nm for s in present),
            min(s.smoothing_rad_s for s in present),
        )

    def torque(self, omega: float) -> float:
        coulomb = self.coulomb_pos if omega >= 0 else self.coulomb_neg
        return self.viscous * omega + coulomb * math.tanh(omega / self.smoothing)


@dataclass(frozen=True)
class Chain:
    """The load as a chain of inertias; DOF 0 is the rotor, the last one carries the sensor.

    Spring i joins DOF i and i+1 with ratio n: its twist is n·θ_i − θ_(i+1), its
    torque acts on DOF i+1 and, times −n, back on DOF i.
    """

    inertias: tuple[float, ...]
    springs: tuple[tuple[float, float, float], ...]
    frictions: tuple[LumpedFriction, ...]

    @property
    def ratios(self) -> tuple[float, ...]:
        return tuple(s[2] for s in self.springs)


def build_chain(unit: UnitParams) -> Chain:
    """Lump the load into the fewest inertias its compliances allow."""
    mech = unit.mechanics
    j_rotor = unit.motor.rotor_inertia_kgm2
    rotor_f: list[FrictionParams | None] = [mech.rotor_bearing]
    load_f: list[FrictionParams | None] = [mech.load_bearing, mech.load_friction]
    coupling = mech.coupling
    if mech.disk is not None:
        if coupling is None:
            return Chain((j_rotor + mech.disk.inertia_kgm2,), (),
                         (LumpedFriction.combine(rotor_f + load_f),))
        return Chain(
            (j_rotor, mech.disk.inertia_kgm2),
            ((coupling.stiffness_Nm_per_rad, coupling.damping_Nms_per_rad, 1.0),),
            (LumpedFriction.combine(rotor_f), LumpedFriction.combine(load_f)),
        )
    belt = mech.belt
    if belt is None:
        raise ValueError("mechanics without a disk need a belt")
    belt_spring = (belt.stiffness_Nm_per_rad, belt.damping_Nms_per_rad, belt.reduction)
    second = belt.second_mode
    if second is not None:
        if coupling is not None:
            raise ValueError("a belt with a second mode takes no coupling at the rotor as well")
        # The load splits at its own compliance: the part beyond it carries the sensor.
        return Chain(
            (j_rotor + belt.motor_pulley_inertia_kgm2,
             (1.0 - second.share) * belt.load_inertia_kgm2,
             second.share * belt.load_inertia_kgm2),
            (belt_spring, (second.stiffness_Nm_per_rad, second.damping_Nms_per_rad, 1.0)),
            (LumpedFriction.combine(rotor_f), LumpedFriction.combine([]),
             LumpedFriction.combine(load_f)),
        )
    if coupling is None:
        return Chain(
            (j_rotor + belt.motor_pulley_inertia_kgm2, belt.load_inertia_kgm2),
            (belt_spring,),
            (LumpedFriction.combine(rotor_f), LumpedFriction.combine(load_f)),
        )
    return Chain(
        (j_rotor, belt.motor_pulley_inertia_kgm2, belt.load_inertia_kgm2),
        ((coupling.stiffness_Nm_per_rad, coupling.damping_Nms_per_rad, 1.0), belt_spring),
        (LumpedFriction.combine(rotor_f), LumpedFriction.combine([]),
         LumpedFriction.combine(load_f)),
    )


@dataclass(frozen=True)
class Mode:
    """A mode of the linearised plant."""

    frequency_hz: float
    damping_ratio: float

    @property
    def decay_rate_per_s(self) -> float:
        return self.damping_ratio * 2.0 * math.pi * self.frequency_hz


def _chain_poles(unit: UnitParams, amplitude_mA: float, load_angle_rad: float = 0.0
                 ) -> NDArray[np.complex128]:
    """Eigenvalues of the linear chain's state matrix, the rotor on its magnetic spring:
    ringing modes in conjugate pairs, and the real poles of any part damped beyond
    critical."""
    chain = build_chain(unit)
    n = len(chain.inertias)
    mass = np.diag(chain.inertias)
    stiff = np.zeros((n, n))
    damp = np.diag([f.viscous for f in chain.frictions])
    stiff[0, 0] = magnetic_stiffness(unit.motor, amplitude_mA, load_angle_rad)
    for i, (k, c, ratio) in enumerate(chain.springs):
        for matrix, coeff in ((stiff, k), (damp, c)):
            matrix[i, i] += coeff * ratio * ratio
            matrix[i, i + 1] -= coeff * ratio
            matrix[i + 1, i] -= coeff * ratio
            matrix[i + 1, i + 1] += coeff
    inv_m = np.linalg.inv(mass)
    state = np.block([[np.zeros((n, n)), np.eye(n)], [-inv_m @ stiff, -inv_m @ damp]])
    poles: NDArray[np.complex128] = np.linalg.eigvals(state).astype(np.complex128)
    return poles


def modal_analysis(unit: UnitParams, amplitude_mA: float, *,
                   load_angle_rad: float = 0.0) -> list[Mode]:
    """Modes of the chain with the rotor on its magnetic spring (``magnetic_stiffness``).

    Coulomb friction is left out: in steady motion its tanh is saturated and
    adds no damping. Sorted by frequency.
    """
    modes = []
    for lam in _chain_poles(unit, amplitude_mA, load_angle_rad):
        if lam.imag > 0:
            wn = abs(lam)
            modes.append(Mode(wn / (2.0 * math.pi), -lam.real / wn))
    return sorted(modes, key=lambda m: m.frequency_hz)


def _lowpass_zoh(bandwidth_hz: float, zeta: float, step_s: float) -> tuple[float, ...]:
    """Exact ZOH discretisation of ω0²/(s² + 2ζω0 s + ω0²), state [y, ẏ]."""
    w0 = 2.0 * math.pi * bandwidth_hz
    a = np.array([[0.0, 1.0], [-w0 * w0, -2.0 * zeta * w0]])
    aug = np.zeros((3, 3))
    aug[:2, :2] = a
    aug[1, 2] = w0 * w0
    d = expm(aug * step_s)
    return (float(d[0, 0]), float(d[0, 1]), float(d[1, 0]), float(d[1, 1]),
            float(d[0, 2]), float(d[1, 2]))


def _lag_coefficients(bandwidth_hz: float | None, step_s: float) -> tuple[float, float, float]:
    """First-order current loop, exact for a target that is linear over a step.

    i(t+h) = a·i(t) + (b − a)·u(t) + (1 − b)·u(t+h), a = e^(−ωh), b = (1 − a)/(ωh).
    """
    if bandwidth_hz is None:
        return 0.0, 0.0, 1.0
    wh = 2.0 * math.pi * bandwidth_hz * step_s
    a = math.exp(-wh)
    b = (1.0 - a) / wh
    return a, b - a, 1.0 - b


def _periodic_tables(terms: dict[int, list[complex]], slots: int) -> NDArray[np.float64]:
    """Tables of Re Σ_j w_j·e^(i·j·φ) over one period, one row per slot, with a wrap point;
    no rows without terms.

    Evaluating a handful of harmonics exactly per step costs far more than an
    interpolated table's two reads.
    """
    if not terms:
        return np.zeros((0, TABLE_SIZE + 1))
    phi = np.arange(TABLE_SIZE + 1) * (2.0 * math.pi / TABLE_SIZE)
    tables = np.zeros((slots, TABLE_SIZE + 1))
    for slot in range(slots):
        for order, weights in terms.items():
            tables[slot] += (weights[slot] * np.exp(1j * order * phi)).real
    return tables


MAX_STEP_PHASE = 0.7
"""|λ|·h of the chain's fastest pole per integration step, at most. Symplectic
Euler keeps a mode stable below 2 and stretches its period by about (ω·h)²/24:
2 % here, and only for modes far above the sensor's band. Its damping is explicit, so a
part damped beyond critical has a real pole that needs the same bound: a belt's pulley
(3.8 µg·m², on a belt of 1,300 N·m/rad and 0.19 N·m·s/rad at the motor) has no mode,
but poles at −8,100 and −43,000 s⁻¹, and at 8 substeps the plant overflowed (benchmark
trial load_resonance@1580042069 ended a run of 85 minutes)."""


def substeps_for(unit: UnitParams, sync_period_s: float, minimum: int) -> int:
    """The fewest substeps per SYNC, at least ``minimum``, that integrate ``unit`` stably.

    A stiff belt on a light rotor rings at kilohertz, and a heavily damped pulley decays
    faster still; at the usual 8 substeps of a 1-ms SYNC either would blow up. The
    magnetic spring is taken at the strongest current the trims allow (1.5 × rated),
    where the modes are highest.
    """
    current = unit.rated_current_mA * GAIN_LIMITS[1] / GAIN_UNITY
    fastest = float(np.max(np.abs(_chain_poles(unit, current)), initial=0.0))
    needed = math.ceil(fastest * sync_period_s / MAX_STEP_PHASE)
    return max(minimum, needed)


def _noise_stream(unit: UnitParams, seed: int) -> np.random.Generator:
    if seed < 0:
        raise ValueError("seed must be >= 0")
    digest = hashlib.sha256(f"{unit.serial}/sensor-noise".encode()).digest()
    return np.random.default_rng(np.random.SeedSequence([int.from_bytes(digest, "big"), seed]))


class Plant:
    """One unit on the bench: motor, load chain and sensor, in simulated time.

    ``substeps`` is a minimum: a unit whose chain rings too fast for it gets
    as many more as ``substeps_for`` says (see ``substeps``).
    """

    def __init__(self, unit: UnitParams, *, sync_period_s: float = 0.001, substeps: int = 8,
                 seed: int = 0) -> None:
        if sync_period_s <= 0 or substeps < 1:
            raise ValueError("the SYNC period must be positive and substeps >= 1")
        self._unit = unit
        self._period = sync_period_s
        substeps = substeps_for(unit, sync_period_s, substeps)
        self._substeps = substeps
        self._h = sync_period_s / substeps
        self._syncs = 0
        motor = unit.motor
        self._nr = float(motor.rotor_teeth)
        self._kt = motor.kt_Nm_per_A
        self._chain = build_chain(unit)
        # Angles, speeds and currents carried between periods, and what a period reports.
        self._state = np.zeros(k_.N_STATE)
        self._command = np.zeros(k_.N_COMMAND)
        self._come_to_rest(rest_angle(motor))
        self._setup_torque(motor)
        self._setup_reshaping(motor)
        self._setup_amplifier(unit.amplifier)
        self._setup_sensor(unit, seed)
        self._constants, self._switches = self._loop_constants()
        # Compiled (or loaded from numba's cache) here, with no step to take, rather than
        # at the first SYNC: that takes seconds with the GIL held, and a bench's device
        # threads and the station's watchdogs are running by then.
        k_.integrate(self._constants, self._switches, self._command.copy(), self._state.copy(),
                     self._harmonics, self._distortion, self._detent_alone, self._steps[:0],
                     self._u_substeps)

    # ----------------------------------------------------------------- set-up
    def _setup_torque(self, motor: MotorParams) -> None:
        """Torque beyond eq. (14) as i_A·F_A(θe) + i_B·F_B(θe) + F_D(θe), tabulated.

        Per order j the weights w make τ_j = Re[(i_A·w_A + i_B·w_B + w_D)·e^(i·j·θe)].
        A saturating or eccentric motor keeps F_D in a table of its own, because
        saturation scales the magnet's part and not the detent's.
        """
        nr, i_f = motor.rotor_teeth, motor.field_current_A
        terms: dict[int, list[complex]] = {}

        def add(order: int, slot: int, coeff: complex) -> None:
            terms.setdefault(order, [0j, 0j, 0j])[slot] += coeff

        # -j·Nr·L·i_f·sin(j·θe + φ) = Re[j·Nr·L·i_f·i·e^(iφ)·e^(i·j·θe)]
        for h in motor.flux_a:
            add(h.order, 0, 1j * h.order * nr * h.amplitude_H * i_f * cmath.exp(1j * h.phase_rad))
        for h in motor.flux_b:
            phase = h.phase_rad - h.order * QUARTER_PITCH_ELECTRICAL
            add(h.order, 1, 1j * h.order * nr * h.amplitude_H * i_f * cmath.exp(1j * phase))
        detent: dict[int, list[complex]] = {}
        for d in motor.detent:
            coeff = 0.5j * d.order * nr * d.amplitude_H * i_f * i_f
            if motor.reshapes_torque:
                # Saturation must not scale detent: it gets its own table.
                detent.setdefault(d.order, [0j])[0] += coeff
            else:
                add(d.order, 2, coeff)
        self._harmonics = _periodic_tables(terms, 3)
        detent_table = _periodic_tables(detent, 1)
        self._detent_alone = detent_table[0] if detent_table.size else np.zeros(0)
        self._reluctance = nr * motor.L1_H
        self._reluctance_unequal = nr * motor.L1_H * motor.L1_unequal

    def _setup_reshaping(self, motor: MotorParams) -> None:
        """Saturation and eccentricity, as one tuple the loop unpacks only if there is one.

        ``None`` for a motor without them: the loop then tests nothing it did
        not test before they existed.
        """
        if not motor.reshapes_torque:
            self._reshaping: tuple[Any, ...] | None = None
            return
        sat = motor.saturation_current_A
        ecc = motor.eccentricity
        self._reshaping = (
            sat is not None, 1.0 / (sat * sat) if sat is not None else 0.0,
            self._detent_alone.size > 0, ecc is not None,
            *((ecc.relative, ecc.phase_rad, ecc.unbalance_Nm, ecc.unbalance_phase_rad)
              if ecc is not None else (0.0, 0.0, 0.0, 0.0)),
        )

    def _setup_amplifier(self, amp: AmplifierParams) -> None:
        self._amp = amp
        terms: dict[int, list[complex]] = {}
        for slot, harmonics, shift in ((0, amp.distortion_a, 0.0),
                                       (1, amp.distortion_b, QUARTER_PITCH_ELECTRICAL)):
            for h in harmonics:
                w = terms.setdefault(h.order, [0j, 0j])
                w[slot] += h.relative * cmath.exp(1j * (h.phase_rad - h.order * shift))
        self._distortion = _periodic_tables(terms, 2)
        self._lag_a = _lag_coefficients(amp.bandwidth_a_hz, self._h)
        self._lag_b = _lag_coefficients(amp.bandwidth_b_hz, self._h)
        self._lagged = amp.bandwidth_a_hz is not None
        self._pi_bandwidths: tuple[float, float] | None = None
        circuit = amp.pi_loop
        if circuit is not None and amp.bandwidth_a_hz and amp.bandwidth_b_hz:
            # The kernel's PI loop reads ωb, R/L and 1/L where the lag's coefficients go.
            wb = (2.0 * math.pi * amp.bandwidth_a_hz, 2.0 * math.pi * amp.bandwidth_b_hz)
            r_over_l = circuit.resistance_ohm / circuit.inductance_H
            self._lag_a = (wb[0], r_over_l, 1.0 / circuit.inductance_H)
            self._lag_b = (wb[1], r_over_l, 1.0 / circuit.inductance_H)
            self._pi_bandwidths = wb
        self._dead = (amp.dead_time_mA * 1e-3, 1e3 / amp.dead_time_knee_mA)
        # Per-command current scale: A from mA, gain error and trim gain folded in.
        self._amp_const = (amp.offset_a_mA * 1e-3, amp.offset_b_mA * 1e-3,
                           (1.0 + amp.gain_error_a) / GAIN_UNITY * 1e-3,
                           (1.0 + amp.gain_error_b) / GAIN_UNITY * 1e-3)

    def _setup_sensor(self, unit: UnitParams, seed: int) -> None:
        s = unit.sensor
        # The ICD promises a bandwidth of at least 40 % of the SYNC rate; a MEMS
        # part ties its filter to its output data rate, so faster SYNC widens it.
        bandwidth = max(s.bandwidth_hz, 0.4 / self._period)
        self._lp_sub = _lowpass_zoh(bandwidth, s.damping_ratio, self._h)
        self._lp_sync = _lowpass_zoh(bandwidth, s.damping_ratio, self._period)
        self._radius = s.radius_m
        self._sigma = replace(s, bandwidth_hz=bandwidth).noise_sigma_mps2()
        self._rng = _noise_stream(unit, seed)
        self._noise: list[list[float]] = [[], [], []]
        self._noise_pos = _NOISE_BLOCK
        order = (s.tangential_axis, s.radial_axis, s.axial_axis)
        self._slot = tuple(order.index(axis) for axis in (Axis.X, Axis.Y, Axis.Z))
        self._xf0 = self._xf1 = 0.0
        # The integrator's acceleration belongs to its substep's start, and the filter
        # holds it over the substep: half a substep late. The reading is taken that much
        # later along the filter's slope (measured at 32 substeps: 15 µs gone at every
        # order, which beside a strong detent torque passed for a current loop's lag).
        self._half_step = 0.5 * self._h
        self._yf0 = self._yf1 = 0.0
        self._minus_radius = -s.radius_m
        # Each step's input to the filter, kept for the sample instant of a drifting clock.
        self._u_substeps = np.zeros(self._substeps)
        # The tangential filter is linear, so one SYNC period of it is
        # x_end = Aⁿ·x_start + Σ_k W_k·u_k: the loop accumulates two sums.
        a00, a01, a10, a11, b0, b1 = self._lp_sub
        step = np.array([[a00, a01], [a10, a11]])
        drive = np.array([b0, b1])
        weights = [np.linalg.matrix_power(step, self._substeps - 1 - k) @ drive
                   for k in range(self._substeps)]
        self._steps = np.array([(k * self._h, float(w[0]), float(w[1]))
                                for k, w in enumerate(weights)])
        whole = np.linalg.matrix_power(step, self._substeps)
        self._lp_period = (float(whole[0, 0]), float(whole[0, 1]), float(whole[1, 0]),
                           float(whole[1, 1]))
        drift = s.clock_drift_ppm * 1e-6
        self._drifting = drift != 0.0
        self._sample_period = self._period * (1.0 + drift)
        self._sample_phase = s.sample_phase
        # Out-of-vocabulary imperfections of the sensor element (UnnamedEffect).
        self._cos_tilt = math.cos(s.tilt_rad)
        self._sin_tilt = math.sin(s.tilt_rad)
        self._nonlinear_c = (s.nonlinearity_c2, s.nonlinearity_c3)
        self._tilted = s.tilt_rad != 0.0
        self._nonlinear = s.nonlinearity_c2 != 0.0 or s.nonlinearity_c3 != 0.0
        # Chosen once, so that a square, linear element costs nothing per sample.
        self._emitter: Callable[[float, float], None] = (
            self._emit_through_element if self._tilted or self._nonlinear else self._emit)
        self.set_sensor_range(s.range_g)
        # Until the first SYNC the sensor holds a reading at rest: gravity only.
        at_rest = (0.0, 0.0, STANDARD_GRAVITY)
        self._reading = (at_rest[self._slot[0]], at_rest[self._slot[1]], at_rest[self._slot[2]])
        self._counts = self._quantise(self._reading)

    # ---------------------------------------------------------------- queries
    @property
    def unit(self) -> UnitParams:
        return self._unit

    @property
    def time_s(self) -> float:
        """Simulated time: SYNC periods advanced times the period."""
        return self._syncs * self._period

    @property
    def sync_period_s(self) -> float:
        return self._period

    @property
    def substeps(self) -> int:
        """Integration steps per SYNC period actually taken (see ``substeps_for``)."""
        return self._substeps

    @property
    def rotor_angle_rad(self) -> float:
        return float(self._state[k_.TH0])

    @property
    def rotor_velocity_rad_s(self) -> float:
        return float(self._state[k_.OM0])

    @property
    def load_angle_rad(self) -> float:
        """Angle of the inertia that carries the sensor (load side of any gearing)."""
        return float(self._state[k_.THL])

    @property
    def load_velocity_rad_s(self) -> float:
        return float(self._state[k_.OML])

    @property
    def phase_currents_A(self) -> tuple[float, float]:
        """Actual phase currents at the last integration step."""
        return float(self._state[k_.I_A]), float(self._state[k_.I_B])

    @property
    def motor_torque_Nm(self) -> float:
        """Electromagnetic torque at the last integration step."""
        return float(self._state[k_.TORQUE])

    @property
    def sensor_reading_mps2(self) -> tuple[float, float, float]:
        """The last sample as the sensor's X, Y, Z before noise and quantisation."""
        return self._reading

    def set_sensor_range(self, range_g: int) -> None:
        if range_g not in SENSOR_RANGES_G:
            raise ValueError(f"sensor range {range_g} g is not one of {SENSOR_RANGES_G}")
        self._range_g = range_g
        self._lsb = range_g * STANDARD_GRAVITY / 32768.0
        self._inv_lsb = 1.0 / self._lsb
        # The element's nonlinearity is a fraction of its full scale, whichever range is set.
        full_scale = range_g * STANDARD_GRAVITY
        c2, c3 = self._nonlinear_c
        self._nl2 = c2 / full_scale
        self._nl3 = c3 / (full_scale * full_scale)

    def sensor_lsb_mps2(self) -> float:
        return self._lsb

    def _come_to_rest(self, theta: float) -> None:
        """The mechanics at rest with the rotor at ``theta``: every compliance unloaded."""
        thetas = [theta]
        for ratio in self._chain.ratios:
            thetas.append(ratio * thetas[-1])
        state = self._state
        state[k_.TH0], state[k_.THL] = thetas[0], thetas[-1]
        if len(thetas) == 3:
            state[k_.TH1] = thetas[1]

    # --------------------------------------------------------------- stepping
    def place_on_trajectory(self, command: DriveCommand) -> None:
        """Put the mechanics in the steady motion the command would settle into.

        Every inertia moves at the commanded speed (through its gearing), each
        compliance carries the friction downstream of it, and the rotor lags
        the stator field by the load angle that balances the total friction.
        Steady-state analyses start here so that only the ripple's own
        transient is left to die out, not a start-up from rest.
        """
        chain = self._chain
        kx = 2.0 * math.pi / (4.0 * command.microsteps_per_fullstep)
        x_u = (command.position_start - STAIRCASE_LAG_MICROSTEPS) * kx
        theta_u = x_u / self._nr
        omega_u = command.velocity * kx / self._nr
        n = len(chain.inertias)
        omegas = [omega_u]
        for ratio in chain.ratios:
            omegas.append(omegas[-1] * ratio)
        carried = [0.0] * len(chain.springs)
        downstream = 0.0
        for i in range(n - 1, 0, -1):
            downstream = chain.frictions[i].torque(omegas[i]) + (
                chain.ratios[i] * downstream if i < n - 1 else 0.0
            )
            carried[i - 1] = downstream
        needed = chain.frictions[0].torque(omegas[0])
        if n > 1:
            needed += chain.ratios[0] * carried[0]
        amp = self._amp
        trims = command.trims
        amplitude = command.amplitude_mA * 1e-3 * 0.5 * (
            (1 + amp.gain_error_a) * trims.gain_a + (1 + amp.gain_error_b) * trims.gain_b
        ) / GAIN_UNITY
        capacity = self._kt * amplitude if command.enabled else 0.0
        if self._reshaping is not None:
            capacity, needed = self._reshaped_balance(capacity, needed, amplitude, theta_u)
        rho = math.asin(max(-1.0, min(1.0, needed / capacity))) if capacity > 0 else 0.0
        thetas = [theta_u - rho / self._nr]
        for i, (k, _c, ratio) in enumerate(chain.springs):
            thetas.append(ratio * thetas[-1] - carried[i] / k)
        state = self._state
        state[k_.TH0], state[k_.OM0] = thetas[0], omegas[0]
        state[k_.THL], state[k_.OML] = thetas[-1], omegas[-1]
        if n == 3:
            state[k_.TH1], state[k_.OM1] = thetas[1], omegas[1]
        if command.enabled:
            i_a, i_b = commanded_currents_A(x_u, command.amplitude_mA, trims, amp)
            state[k_.I_A] = state[k_.T_A] = float(i_a)
            state[k_.I_B] = state[k_.T_B] = float(i_b)
            if self._pi_bandwidths is not None:
                # A PI loop's integrator holds the current over its bandwidth at rest.
                state[k_.T_A] = float(i_a) / self._pi_bandwidths[0]
                state[k_.T_B] = float(i_b) / self._pi_bandwidths[1]
        else:
            state[k_.I_A] = state[k_.I_B] = state[k_.T_A] = state[k_.T_B] = 0.0
        self._xf0 = self._xf1 = 0.0
        self._yf0, self._yf1 = -self._radius * omegas[-1] ** 2, 0.0

    def _reshaped_balance(self, capacity: float, needed: float, amplitude_A: float,
                          theta: float) -> tuple[float, float]:
        """The magnet's peak torque and the load it must carry at rotor angle θ.

        Saturation at |i| = I and the eccentric airgap there scale the peak;
        the unbalance's gravity adds to the load.
        """
        motor = self._unit.motor
        capacity *= float(motor.saturation_factor(amplitude_A))
        ecc = motor.eccentricity
        if ecc is not None:
            capacity *= float(ecc.modulation(theta))
            needed += ecc.unbalance_Nm * math.sin(theta + ecc.unbalance_phase_rad)
        return capacity, needed

    def advance(self, command: DriveCommand) -> tuple[int, int, int]:
        """Advance one SYNC period; return the sensor's X, Y, Z counts sampled at the end
        instant (the next SYNC): bandwidth-limited, noisy, 16-bit, saturating at ±32767."""
        if command.microsteps_per_fullstep < 1 or command.amplitude_mA < 0:
            raise ValueError("a command needs microsteps >= 1 and a non-negative amplitude")
        x_start = self._xf0, self._xf1
        y_start = self._yf0
        self._integrate(command)
        self._syncs += 1
        # Radial acceleration changes slowly; filtering it at the SYNC rate is enough.
        a00, a01, a10, a11, b0, b1 = self._lp_sync
        y0, y1 = y_start, self._yf1
        u = self._minus_radius * float(self._state[k_.OML]) ** 2
        self._yf0 = a00 * y0 + a01 * y1 + b0 * u
        self._yf1 = a10 * y0 + a11 * y1 + b1 * u
        if not self._drifting:
            self._emitter(self._xf0 + self._half_step * self._xf1, self._yf0)
            return self._counts
        t_end = self._syncs * self._period
        latest = math.floor(t_end / self._sample_period - self._sample_phase)
        instant = (latest + self._sample_phase) * self._sample_period
        into = instant - (t_end - self._period)
        if into <= 0.0:
            # The sensor's clock is slower: no new sample since the last SYNC.
            return self._counts
        # Replay the filter over this period's inputs to find it at the sample instant.
        a00, a01, a10, a11, b0, b1 = self._lp_sub
        x0, x1 = x_start
        xs = [x0 + self._half_step * x1]
        for u in self._u_substeps.tolist():
            x0, x1 = a00 * x0 + a01 * x1 + b0 * u, a10 * x0 + a11 * x1 + b1 * u
            xs.append(x0 + self._half_step * x1)
        q = into / self._h
        k = min(int(q), self._substeps - 1)
        frac = q - k
        tangential = xs[k] + (xs[k + 1] - xs[k]) * frac
        radial = y_start + (self._yf0 - y_start) * (into / self._period)
        self._emitter(tangential, radial)
        return self._counts

    def _emit(self, tangential: float, radial: float, axial: float = STANDARD_GRAVITY) -> None:
        """Turn the filtered tangential/radial values into the sensor's noisy counts."""
        slot = self._slot
        values = (tangential, radial, axial)
        reading = (values[slot[0]], values[slot[1]], values[slot[2]])
        self._reading = reading
        if self._sigma > 0.0:
            pos = self._noise_pos
            if pos >= _NOISE_BLOCK:
                self._noise = (self._rng.standard_normal((3, _NOISE_BLOCK)) * self._sigma).tolist()
                pos = 0
            noise = self._noise
            self._noise_pos = pos + 1
            reading = (reading[0] + noise[0][pos], reading[1] + noise[1][pos],
                       reading[2] + noise[2][pos])
        self._counts = self._quantise(reading)

    def _emit_through_element(self, tangential: float, radial: float) -> None:
        """``_emit`` for a sensor whose element is turned or nonlinear (``UnnamedEffect``)."""
        values = self._element(tangential, radial)
        self._emit(values[0], values[1], values[2])

    def _element(self, tangential: float, radial: float) -> tuple[float, float, float]:
        """What a turned, nonlinear sensing element makes of the fixture's accelerations.

        Turned by α about the axial axis, its tangential axis reads
        cos α·a_t + sin α·a_r and its radial axis cos α·a_r − sin α·a_t; then
        each axis's transfer bends as a + c2·a²/FS + c3·a³/FS² (FS the full
        scale in m/s²). Applied to the filtered values: the filter is linear
        and the same on every axis, and the signal lies well inside its band.
        """
        values = (tangential, radial, STANDARD_GRAVITY)
        if self._tilted:
            c, s = self._cos_tilt, self._sin_tilt
            values = (c * tangential + s * radial, c * radial - s * tangential, STANDARD_GRAVITY)
        if self._nonlinear:
            k2, k3 = self._nl2, self._nl3
            values = (values[0] + (k2 + k3 * values[0]) * values[0] * values[0],
                      values[1] + (k2 + k3 * values[1]) * values[1] * values[1],
                      values[2] + (k2 + k3 * values[2]) * values[2] * values[2])
        return values

    def _quantise(self, values: tuple[float, float, float]) -> tuple[int, int, int]:
        inv = self._inv_lsb
        full = SATURATED_COUNTS
        cx = round(values[0] * inv)
        cy = round(values[1] * inv)
        cz = round(values[2] * inv)
        return (
            full if cx > full else -full if cx < -full else cx,
            full if cy > full else -full if cy < -full else cy,
            full if cz > full else -full if cz < -full else cz,
        )

    def _loop_constants(self) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
        """What the compiled loop reads of the unit: its constants and its switches."""
        chain = self._chain
        ndof = len(chain.inertias)
        f0, fl = chain.frictions[0], chain.frictions[-1]
        k1, c1, n1 = chain.springs[0] if ndof > 1 else (0.0, 0.0, 0.0)
        k2, c2, n2 = chain.springs[1] if ndof > 2 else (0.0, 0.0, 0.0)
        reshaping = self._reshaping
        saturating, inv_isat2, detent_alone, eccentric, *eccentricity = (
            reshaping if reshaping is not None else (False, 0.0, False, False, 0.0, 0.0, 0.0, 0.0))
        constants = np.array([
            self._h, self._nr, self._kt, self._reluctance, *self._lag_a, *self._lag_b,
            f0.viscous, f0.coulomb_pos, f0.coulomb_neg, 1.0 / f0.smoothing,
            fl.viscous, fl.coulomb_pos, fl.coulomb_neg, 1.0 / fl.smoothing,
            chain.inertias[0], chain.inertias[1] if ndof == 3 else 1.0, chain.inertias[-1],
            k1, c1, n1, k2, c2, n2, self._radius / self._h, inv_isat2, *eccentricity,
            self._reluctance_unequal, *self._dead,
        ], dtype=np.float64)
        switches = np.zeros(k_.N_SWITCHES, dtype=np.int64)
        switches[k_.NDOF] = ndof
        switches[k_.HARMONICS] = self._harmonics.shape[0] > 0
        switches[k_.DISTORTION] = self._distortion.shape[0] > 0
        switches[k_.LAGGED] = self._lagged
        switches[k_.COULOMB_L] = fl.coulomb_pos > 0.0 or fl.coulomb_neg > 0.0
        switches[k_.BEYOND] = self._reluctance != 0.0 or reshaping is not None
        switches[k_.RESHAPING] = reshaping is not None
        switches[k_.SATURATING] = saturating
        switches[k_.DETENT_ALONE] = detent_alone
        switches[k_.ECCENTRIC] = eccentric
        switches[k_.DRIFTING] = self._drifting
        switches[k_.DEAD_TIME] = self._dead[0] > 0.0
        switches[k_.PI_LOOP] = self._pi_bandwidths is not None
        if constants.size != k_.N_CONSTANTS:
            raise AssertionError("the plant's constants do not match the kernel's layout")
        return constants, switches

    def _integrate(self, command: DriveCommand) -> None:
        """One SYNC period of the compiled loop (``kernel.integrate``), then the sensor
        filter's state at its end from the two sums the loop accumulated."""
        trims = command.trims
        amp_off_a, amp_off_b, amp_gain_a, amp_gain_b = self._amp_const
        # The drive commands its currents from its integer position demand (the
        # microstep staircase, ICD.md §2). The staircase's steps come at the
        # microstep rate (20 kHz at 20 Hz electrical), far above the mechanics
        # and the sensor; sampled at the substep rate they would alias onto low
        # harmonics, which is not physics. So the currents follow the staircase's
        # mean: the ramp p(t) = p0 + (pv + pa·t)·t, half a microstep behind.
        # One slice assignment in ``kernel``'s order (ENABLED … FB).
        cmd = self._command
        cmd[:] = (
            1.0 if command.enabled else 0.0,
            2.0 * math.pi / (4.0 * command.microsteps_per_fullstep),
            command.position_start - STAIRCASE_LAG_MICROSTEPS,
            command.velocity,
            0.5 * command.acceleration,
            trims.offset_a_mA * 1e-3 + amp_off_a,
            trims.offset_b_mA * 1e-3 + amp_off_b,
            amp_gain_a * trims.gain_a * command.amplitude_mA,
            amp_gain_b * trims.gain_b * command.amplitude_mA,
        )
        state = self._state
        k_.integrate(self._constants, self._switches, cmd, state, self._harmonics,
                     self._distortion, self._detent_alone, self._steps, self._u_substeps)
        p00, p01, p10, p11 = self._lp_period
        xs0, xs1 = self._xf0, self._xf1
        acc0, acc1 = state[k_.ACC0:k_.ACC1 + 1].tolist()
        self._xf0 = p00 * xs0 + p01 * xs1 + acc0
        self._xf1 = p10 * xs0 + p11 * xs1 + acc1
