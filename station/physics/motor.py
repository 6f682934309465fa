"""The paper's torque model of a two-phase hybrid stepper motor, eq. (1)-(18).

The torque is the co-energy derivative τ = ½ iᵀ (∂L/∂θ) i of a 3x3 inductance
matrix over the two phase currents and a fictitious field current i_f that
stands for the permanent magnet (eq. 1-2). Entries follow eq. (4)-(9) with one
generalisation (the ``flux_harmonics`` effect): the paper writes L2f with
``sin(j·Nr·θ)`` for every harmonic, which is only right for j = 1. Phase B sits
a quarter tooth pitch from phase A, so a motor whose phases are alike has
L2f(θ) = L1f(θ − π/(2·Nr)); real phases are not quite alike, so each phase
carries its own amplitude and phase per harmonic.

Units are SI throughout: currents in A, inductances in H, angles in rad
(mechanical unless named electrical), torque in N·m.

Two effects reshape that torque without changing L(θ)'s form (see
``MotorParams.saturation_factor`` and ``Eccentricity``): the magnet torque
falls with the stator current as the iron saturates, and an eccentric rotor's
airgap torque varies once per mechanical revolution. They make τ no longer the
co-energy derivative of a fixed L(θ), so ``torque`` and ``torque_components``
apply them to eq. (3)'s parts explicitly.

Eq. (18) as printed, |τ2| = Kt·¼·|I11 − I21|, disagrees by a factor of two with
eq. (16) from which it is derived; the magnitude that eq. (16) (and eq. (1))
actually produce is Kt·½·|I11 − I21|, and that is what is implemented here.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

FloatArray = NDArray[np.float64]

QUARTER_PITCH_ELECTRICAL = math.pi / 2.0
"""Phase B's offset from phase A in electrical radians (a quarter tooth pitch)."""


@dataclass(frozen=True)
class FluxHarmonic:
    """One harmonic j ≥ 2 of a phase's mutual inductance to the magnet.

    Phase A contributes ``amplitude_H·cos(j·Nr·θ + phase_rad)`` to L1f;
    phase B contributes ``amplitude_H·cos(j·(Nr·θ − π/2) + phase_rad)`` to L2f,
    so equal entries on both phases mean equal, quarter-pitch-shifted phases.
    """

    order: int
    amplitude_H: float
    phase_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.order < 2:
            raise ValueError(f"flux harmonic order must be >= 2 (j = 1 is Lm1), got {self.order}")


@dataclass(frozen=True)
class DetentHarmonic:
    """One harmonic of the magnet's self-inductance L_ff, eq. (9): Lfj·cos(j·Nr·θ)."""

    order: int
    amplitude_H: float

    def __post_init__(self) -> None:
        if self.order < 1:
            raise ValueError(f"detent harmonic order must be >= 1, got {self.order}")


@dataclass(frozen=True)
class Eccentricity:
    """A rotor that is not centred in the stator bore (``rotor_eccentricity``).

    The airgap is narrowest at one point of the rotor's circumference, so the
    permeance through which every torque crosses the gap (magnet, reluctance,
    detent) varies once per mechanical revolution: the airgap torque is
    multiplied by 1 + relative·cos(θ + phase_rad), θ the rotor's mechanical
    angle (not N_r·θ). The rotor's mass centre is off the axis with it, so
    gravity adds a load −unbalance_Nm·sin(θ + unbalance_phase_rad) on the
    rotor; that is a load, not motor torque, and only the plant applies it.
    """

    relative: float
    phase_rad: float
    unbalance_Nm: float = 0.0
    unbalance_phase_rad: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.relative < 1.0:
            raise ValueError(f"eccentricity {self.relative} is not a fraction of the airgap")
        if self.unbalance_Nm < 0:
            raise ValueError("the unbalance torque is a magnitude (>= 0)")

    def modulation(self, theta: ArrayLike) -> FloatArray:
        """1 + relative·cos(θ + phase_rad): the airgap torque's factor at rotor angle θ."""
        th = np.asarray(theta, dtype=np.float64)
        return np.asarray(1.0 + self.relative * np.cos(th + self.phase_rad), dtype=np.float64)


def saturation_current_for_drop(rated_A: float, drop: float) -> float:
    """I_s that makes the torque constant ``drop`` (a fraction) lower at ``rated_A``.

    From 1/√(1 + (I/I_s)²) = 1 − drop (see ``MotorParams.saturation_factor``).
    """
    if rated_A <= 0 or not 0.0 < drop < 1.0:
        raise ValueError("need a positive rated current and a drop in (0, 1)")
    return rated_A / math.sqrt(1.0 / (1.0 - drop) ** 2 - 1.0)


@dataclass(frozen=True)
class MotorParams:
    """Electromagnetic constants of one motor, eq. (4)-(9), plus its rotor inertia.

    ``L1_H`` is the reluctance variation of eq. (4)-(6) (zero under assumption
    (10)); ``L1_unequal`` makes the two phases' own variations unequal, L1·(1 + u) in
    L11 and L1·(1 − u) in L22 (a motor whose phases' teeth or windings differ): on top of
    the paper's spring it adds a torque at twice the electrical angle growing with
    |i|², −Nr·L1·u·sin 2θe·(i_A² + i_B²). ``flux_a``/``flux_b`` hold the harmonics j ≥ 2
    of L1f/L2f (empty under (10)); ``detent`` holds the L_ff harmonics of eq. (9).
    ``saturation_current_A`` is I_s of ``saturation_factor`` (``None``: the
    iron never saturates); ``eccentricity`` is ``None`` for a centred rotor.
    """

    rotor_teeth: int = 50
    field_current_A: float = 10.0
    L0_H: float = 4.0e-3
    L1_H: float = 0.0
    L1_unequal: float = 0.0
    Lm0_H: float = 0.2e-3
    Lm1_H: float = 0.8e-3
    flux_a: tuple[FluxHarmonic, ...] = ()
    flux_b: tuple[FluxHarmonic, ...] = ()
    Lf0_H: float = 0.05
    detent: tuple[DetentHarmonic, ...] = ()
    rotor_inertia_kgm2: float = 6.0e-6
    saturation_current_A: float | None = None
    eccentricity: Eccentricity | None = None

    def __post_init__(self) -> None:
        if self.rotor_teeth < 1:
            raise ValueError("a motor needs at least one rotor tooth")
        if self.field_current_A <= 0 or self.Lm1_H <= 0 or self.rotor_inertia_kgm2 <= 0:
            raise ValueError("field current, Lm1 and rotor inertia must be positive")
        if self.saturation_current_A is not None and self.saturation_current_A <= 0:
            raise ValueError("the saturation current must be positive")
        if not -1.0 < self.L1_unequal < 1.0:
            raise ValueError("unequal phases' reluctance is a fraction of L1 within (-1, 1)")

    def saturation_factor(self, current_A: ArrayLike) -> FloatArray:
        """g(|i|) = 1/√(1 + (|i|/I_s)²), the magnet torque's factor (``magnetic_saturation``).

        The stator's MMF drives the teeth's iron towards saturation, so the
        flux the magnet torque rides on grows less than in proportion to the
        current vector's magnitude |i| = √(i_A² + i_B²), whatever its
        direction. This law is smooth and even in the currents, 1 at zero
        current, and keeps g·|i| rising towards I_s like a magnetisation
        curve instead of falling back (as 1/(1 + (|i|/I_s)²) would beyond
        I_s). It scales everything proportional to the phase currents through
        L1f/L2f: Kt's fundamental and the flux harmonics, not reluctance or
        detent. 1 exactly without saturation.
        """
        i = np.asarray(current_A, dtype=np.float64)
        if self.saturation_current_A is None:
            return np.ones_like(i)
        x = i / self.saturation_current_A
        return np.asarray(1.0 / np.sqrt(1.0 + x * x), dtype=np.float64)

    @property
    def kt_Nm_per_A(self) -> float:
        """Torque constant Kt = i_f·Lm1·Nr, the factor in front of eq. (14)-(18)."""
        return self.field_current_A * self.Lm1_H * self.rotor_teeth

    def holding_torque_Nm(self, amplitude_A: float) -> float:
        """Peak of the static torque curve Kt·I sin ρ of eq. (14).

        The paper's, at the low-current Kt: effects are sized against it, so
        saturation (``saturation_factor``) is left out.
        """
        return self.kt_Nm_per_A * amplitude_A

    @property
    def reshapes_torque(self) -> bool:
        """Whether saturation or eccentricity take τ beyond eq. (1) of a fixed L(θ)."""
        return self.saturation_current_A is not None or self.eccentricity is not None


def _angles(theta: ArrayLike) -> FloatArray:
    return np.asarray(theta, dtype=np.float64)


def mutual_inductances(theta: ArrayLike, motor: MotorParams) -> tuple[FloatArray, FloatArray]:
    """L1f and L2f of eq. (7)-(8), generalised with per-phase harmonics."""
    th = _angles(theta)
    te = motor.rotor_teeth * th
    l1f = motor.Lm0_H + motor.Lm1_H * np.cos(te)
    l2f = motor.Lm0_H + motor.Lm1_H * np.cos(te - QUARTER_PITCH_ELECTRICAL)
    for h in motor.flux_a:
        l1f = l1f + h.amplitude_H * np.cos(h.order * te + h.phase_rad)
    for h in motor.flux_b:
        l2f = l2f + h.amplitude_H * np.cos(h.order * (te - QUARTER_PITCH_ELECTRICAL) + h.phase_rad)
    return l1f, l2f


def _mutual_derivatives(th: FloatArray, motor: MotorParams) -> tuple[FloatArray, FloatArray]:
    nr = motor.rotor_teeth
    te = nr * th
    d1f = -nr * motor.Lm1_H * np.sin(te)
    d2f = -nr * motor.Lm1_H * np.sin(te - QUARTER_PITCH_ELECTRICAL)
    for h in motor.flux_a:
        d1f = d1f - h.order * nr * h.amplitude_H * np.sin(h.order * te + h.phase_rad)
    for h in motor.flux_b:
        d2f = d2f - h.order * nr * h.amplitude_H * np.sin(
            h.order * (te - QUARTER_PITCH_ELECTRICAL) + h.phase_rad
        )
    return d1f, d2f


def inductance_matrix(theta: ArrayLike, motor: MotorParams) -> FloatArray:
    """L(θ) of eq. (2) with entries (4)-(9); shape ``θ.shape + (3, 3)``."""
    th = _angles(theta)
    nr = motor.rotor_teeth
    te = nr * th
    l1a = motor.L1_H * (1.0 + motor.L1_unequal)
    l1b = motor.L1_H * (1.0 - motor.L1_unequal)
    l11 = motor.L0_H + l1a * np.cos(2 * te)
    l22 = motor.L0_H - l1b * np.cos(2 * te)
    l12 = -motor.L0_H / 2 + motor.L1_H * np.sin(2 * te)
    l1f, l2f = mutual_inductances(th, motor)
    lff = np.full_like(te, motor.Lf0_H)
    for d in motor.detent:
        lff = lff + d.amplitude_H * np.cos(d.order * te)
    out = np.empty((*th.shape, 3, 3))
    out[..., 0, 0] = l11
    out[..., 1, 1] = l22
    out[..., 0, 1] = out[..., 1, 0] = l12
    out[..., 0, 2] = out[..., 2, 0] = l1f
    out[..., 1, 2] = out[..., 2, 1] = l2f
    out[..., 2, 2] = lff
    return out


def inductance_matrix_derivative(theta: ArrayLike, motor: MotorParams) -> FloatArray:
    """∂L/∂θ (analytic, per mechanical radian); shape ``θ.shape + (3, 3)``."""
    th = _angles(theta)
    nr = motor.rotor_teeth
    te = nr * th
    d11 = -2 * nr * motor.L1_H * (1.0 + motor.L1_unequal) * np.sin(2 * te)
    d22 = 2 * nr * motor.L1_H * (1.0 - motor.L1_unequal) * np.sin(2 * te)
    d12 = 2 * nr * motor.L1_H * np.cos(2 * te)
    d1f, d2f = _mutual_derivatives(th, motor)
    dff = np.zeros_like(te)
    for d in motor.detent:
        dff = dff - d.order * nr * d.amplitude_H * np.sin(d.order * te)
    out = np.empty((*th.shape, 3, 3))
    out[..., 0, 0] = d11
    out[..., 1, 1] = d22
    out[..., 0, 1] = out[..., 1, 0] = d12
    out[..., 0, 2] = out[..., 2, 0] = d1f
    out[..., 1, 2] = out[..., 2, 1] = d2f
    out[..., 2, 2] = dff
    return out


def _current_vector(i_a: ArrayLike, i_b: ArrayLike, shape: tuple[int, ...],
                    i_f: float) -> FloatArray:
    ia = np.broadcast_to(np.asarray(i_a, dtype=np.float64), shape)
    ib = np.broadcast_to(np.asarray(i_b, dtype=np.float64), shape)
    return np.stack([ia, ib, np.full(shape, i_f)], axis=-1)


def _quadratic_form(matrix: FloatArray, theta: FloatArray, i_a: ArrayLike, i_b: ArrayLike,
                    i_f: float) -> FloatArray:
    shape = np.broadcast_shapes(theta.shape, np.shape(i_a), np.shape(i_b))
    m = np.broadcast_to(matrix, (*shape, 3, 3))
    i = _current_vector(i_a, i_b, shape, i_f)
    return np.asarray(0.5 * np.einsum("...i,...ij,...j->...", i, m, i), dtype=np.float64)


def _components(d: FloatArray, theta: FloatArray, i_a: ArrayLike, i_b: ArrayLike,
                motor: MotorParams) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Eq. (3)'s parts from ∂L/∂θ, with saturation on τ_pm and eccentricity on all three."""
    ia = np.asarray(i_a, dtype=np.float64)
    ib = np.asarray(i_b, dtype=np.float64)
    i_f = motor.field_current_A
    pm = d[..., 0, 2] * ia * i_f + d[..., 1, 2] * ib * i_f
    vr = 0.5 * d[..., 0, 0] * ia**2 + 0.5 * d[..., 1, 1] * ib**2 + d[..., 0, 1] * ia * ib
    cg = np.broadcast_to(0.5 * d[..., 2, 2] * i_f**2, np.shape(pm))
    if motor.saturation_current_A is not None:
        pm = pm * motor.saturation_factor(np.sqrt(ia * ia + ib * ib))
    if motor.eccentricity is not None:
        m = motor.eccentricity.modulation(theta)
        pm, vr, cg = pm * m, vr * m, cg * m
    return (np.asarray(pm, dtype=np.float64), np.asarray(vr, dtype=np.float64),
            np.asarray(cg, dtype=np.float64))


def _torque_from_derivative(d: FloatArray, theta: FloatArray, i_a: ArrayLike, i_b: ArrayLike,
                            motor: MotorParams) -> FloatArray:
    if not motor.reshapes_torque:
        return _quadratic_form(d, theta, i_a, i_b, motor.field_current_A)
    pm, vr, cg = _components(d, theta, i_a, i_b, motor)
    return np.asarray(pm + vr + cg, dtype=np.float64)


def torque(theta: ArrayLike, i_a: ArrayLike, i_b: ArrayLike, motor: MotorParams) -> FloatArray:
    """Eq. (1): τ = ½ iᵀ ∂L/∂θ i with i = [i_a, i_b, i_f], analytic derivative.

    With saturation or eccentricity, τ = m(θ)·(g(|i|)·τ_pm + τ_vr + τ_cg) (see
    ``MotorParams.saturation_factor`` and ``Eccentricity``).
    """
    th = _angles(theta)
    return _torque_from_derivative(inductance_matrix_derivative(th, motor), th, i_a, i_b, motor)


def torque_numerical(theta: ArrayLike, i_a: ArrayLike, i_b: ArrayLike, motor: MotorParams, *,
                     step_rad: float = 1e-7) -> FloatArray:
    """Eq. (1) with ∂L/∂θ by central difference: an independent check of the analytic one."""
    th = _angles(theta)
    d_l = (inductance_matrix(th + step_rad, motor) - inductance_matrix(th - step_rad, motor)) / (
        2 * step_rad
    )
    return _torque_from_derivative(d_l, th, i_a, i_b, motor)


def torque_components(theta: ArrayLike, i_a: ArrayLike, i_b: ArrayLike,
                      motor: MotorParams) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Eq. (3): magnet (τ_pm), reluctance (τ_vr) and cogging (τ_cg) torques.

    Saturation scales τ_pm, eccentricity all three, so they still add up to ``torque``.
    """
    th = _angles(theta)
    return _components(inductance_matrix_derivative(th, motor), th, i_a, i_b, motor)


def torque_closed_form(theta: ArrayLike, theta_u: ArrayLike, motor: MotorParams, *, I10: float,
                       I20: float, I11: float, I21: float) -> FloatArray:
    """Eq. (16): τ_pm for the excitation (15) under assumptions (10).

    ``theta_u`` is the stator flux angle (mechanical), so N_r·θ_u is the
    electrical angle x_u of the drive's sine/cosine table.
    """
    nr = motor.rotor_teeth
    th = _angles(theta)
    tu = _angles(theta_u)
    kt = motor.kt_Nm_per_A
    out = kt * (
        0.5 * (I11 + I21) * np.sin(nr * (tu - th))
        - I10 * np.sin(nr * th)
        + I20 * np.cos(nr * th)
        - 0.5 * (I11 - I21) * np.sin(nr * (th + tu))
    )
    return np.asarray(out, dtype=np.float64)


def ripple_harmonic_magnitudes(motor: MotorParams, I10: float, I20: float, I11: float,
                               I21: float) -> tuple[float, float]:
    """Magnitudes of the 1st and 2nd torque-ripple harmonics, eq. (17)-(18).

    The 2nd uses ½·|I11 − I21|, the value eq. (16) gives (see the module note
    on the paper's ¼).
    """
    kt = motor.kt_Nm_per_A
    return kt * math.hypot(I10, I20), kt * 0.5 * abs(I11 - I21)


def magnetic_stiffness(motor: MotorParams, amplitude_mA: float,
                       load_angle_rad: float = 0.0) -> float:
    """dτ/dθ of the rotor on the stator field (N·m per mechanical rad), balanced currents.

    This is the spring the rotor rides on, so it sets the rotor's natural
    frequency and hence how torque ripple becomes acceleration ripple. The
    magnet gives Kt·I·Nr·cos ρ (ρ the electrical load angle); the reluctance
    torque Nr·L1·I²·sin 2ρ adds 2·Nr²·L1·I²·cos 2ρ. Detent is left out: its
    stiffness depends on where the rotor is, not on ρ, and averages out in motion.
    Saturation lowers the magnet's part by g(I) (|i| = I on balanced currents,
    so g does not vary with θ); eccentricity averages out over a revolution.
    """
    current = amplitude_mA * 1e-3
    nr = motor.rotor_teeth
    magnet = motor.kt_Nm_per_A * float(motor.saturation_factor(current))
    return (magnet * current * nr * math.cos(load_angle_rad)
            + 2.0 * nr * nr * motor.L1_H * current * current * math.cos(2.0 * load_angle_rad))


_REST_GRID_PER_DETENT = 32
"""Grid points per detent period when looking for a disabled rotor's rest angle."""
_REST_SPAN_DETENTS = 4
"""Detent periods either side of the unbalance's low point searched for a balance."""


def rest_angle(motor: MotorParams) -> float:
    """Where a disabled eccentric rotor comes to rest: its mechanical angle.

    A unit arrives at the station having sat on the fixture: its rotor is at
    rest where gravity on the unbalance and the detent torque balance, not
    wherever an angle of 0 happens to be. Started elsewhere, a rotor whose
    bearings carry no Coulomb friction swings for seconds, which the sensor's
    standstill check sees (0.2-9.9 m/s² rms on 8 of 200 drawn units) though no
    real unit would. Of the stable balances (static torque falling through
    zero) the one nearest the unbalance's low point is taken: the rotor creeps
    downhill until a detent holds it. 0.0 for a balanced rotor.
    """
    ecc = motor.eccentricity
    if ecc is None or ecc.unbalance_Nm == 0.0:
        return 0.0

    def static(theta: ArrayLike) -> FloatArray:
        th = np.asarray(theta, dtype=np.float64)
        return np.asarray(torque(th, 0.0, 0.0, motor)
                          - ecc.unbalance_Nm * np.sin(th + ecc.unbalance_phase_rad),
                          dtype=np.float64)

    low = math.remainder(-ecc.unbalance_phase_rad, 2.0 * math.pi)
    # One detent period is a quarter tooth pitch; a few either side of the low
    # point hold the balance a detent can make.
    pitch = 2.0 * math.pi / (4.0 * motor.rotor_teeth)
    span = _REST_SPAN_DETENTS * pitch
    grid = low + np.linspace(-span, span, 2 * _REST_GRID_PER_DETENT * _REST_SPAN_DETENTS + 1)
    values = static(grid)
    falling = np.flatnonzero((values[:-1] > 0.0) & (values[1:] <= 0.0))
    if falling.size == 0:
        return low
    nearest = falling[np.argmin(np.abs(grid[falling] - low))]
    a, b = float(grid[nearest]), float(grid[nearest + 1])
    for _ in range(60):
        mid = 0.5 * (a + b)
        if float(static(mid)) > 0.0:
            a = mid
        else:
            b = mid
    return 0.5 * (a + b)
