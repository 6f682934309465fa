"""A simulated unit: every constant of motor, drive, load and sensor, from its serial.

The simulator must behave like a population of real units: each serial has its
own amplifier offsets and gain errors (what calibration removes) and, for some
units, concealed extra physics (``Effect``) that a diagnosis should find. All
of it is drawn from a numpy Generator seeded with SHA-256 of the serial label,
so a unit is the same in every process and on every machine (Python's
``hash()`` is salted per process and would not be).

Every group of constants draws from its own stream, and every effect's
constants are drawn whether or not the effect is on: switching an effect on
(``effects=[...]``) reveals the same magnitudes the unit would conceal, and
adding a new group later does not reshuffle existing units.
"""

from __future__ import annotations

import hashlib
import math
from collections.abc import Iterable
from dataclasses import dataclass, fields, is_dataclass, replace
from enum import Enum, StrEnum
from typing import Any

import numpy as np

from station.core import SENSOR_RANGES_G, STANDARD_GRAVITY, Axis, Effect, LoadKind
from station.physics.motor import (
    DetentHarmonic,
    Eccentricity,
    FluxHarmonic,
    MotorParams,
    saturation_current_for_drop,
)
from station.serials import parse_serial

__all__ = [
    "AmplifierParams",
    "Axis",
    "BeltParams",
    "CouplingParams",
    "CurrentHarmonic",
    "DetentHarmonic",
    "DiskParams",
    "Eccentricity",
    "EffectForm",
    "FluxHarmonic",
    "FrictionParams",
    "MechanicsParams",
    "MotorParams",
    "PhaseCircuit",
    "SecondModeParams",
    "SensorParams",
    "UnitParams",
    "UnnamedEffect",
    "derive_unit",
]



NOMINAL_ELECTRICAL_HZ = 20.0
"""The paper's driving frequency; friction and smoothing are scaled to it."""

EFFECT_PROBABILITY = 0.2
"""Chance that a unit conceals any one effect (so most units have few or none)."""

BELT_REDUCTION = 1.0 / 7.0
"""The paper's pan unit: N_G = 1/7 (load revolutions per motor revolution)."""


class UnnamedEffect(StrEnum):
    """Physics that no id of the effect vocabulary (``Effect``, CLI.md) describes.

    A simulated unit may carry these so that a diagnosis can be tried on
    what it has no name for: the honest answer is a located mismatch without
    an id, never the nearest ``Effect``. Kept out of ``Effect`` on purpose,
    so nothing can name them.
    """

    SENSOR_NONLINEARITY = "sensor_nonlinearity"
    SENSOR_TILT = "sensor_tilt"


class EffectForm(StrEnum):
    """Another physical form of a vocabulary id than the one the simulator draws by default.

    The world makes most effects more than one way, and other simulators and benches
    model them their own way: a name must not depend on the form ours happens to use.
    """

    DEAD_TIME = "dead_time"
    """``current_distortion`` from the bridge's dead time (``AmplifierParams.dead_time_mA``)
    instead of a harmonic waveform."""
    UNEQUAL_PHASES = "unequal_phases"
    """``reluctance_torque`` with the two phases' reluctance unequal
    (``MotorParams.L1_unequal``): a torque at twice the electrical angle growing with |i|²."""
    PI_LOOP = "pi_loop"
    """``current_loop_lag`` as PI loops on the phases' resistance and inductance, tuned to
    the drawn bandwidths, with the motor's back-EMF acting on them
    (``AmplifierParams.pi_loop``), instead of a first-order lag of the command alone."""
    SECOND_BELT_MODE = "second_belt_mode"
    """``load_resonance`` beyond a declared belt instead of at the rotor: part of the load
    on a compliance of its own (``BeltParams.second_mode``), a second mode of the belt's
    chain. Belts only."""

    @property
    def effect(self) -> Effect:
        """The id this is a form of."""
        return {EffectForm.DEAD_TIME: Effect.CURRENT_DISTORTION,
                EffectForm.UNEQUAL_PHASES: Effect.RELUCTANCE_TORQUE,
                EffectForm.PI_LOOP: Effect.CURRENT_LOOP_LAG,
                EffectForm.SECOND_BELT_MODE: Effect.LOAD_RESONANCE}[self]


@dataclass(frozen=True)
class CurrentHarmonic:
    """A harmonic of one phase's current waveform, relative to its fundamental.

    Phase A adds ``relative·Î·cos(h·x_u + phase_rad)``; phase B the same with
    x_u − π/2 (its own waveform angle), so equal entries mean equal phases.
    """

    order: int
    relative: float
    phase_rad: float = 0.0

    def __post_init__(self) -> None:
        if self.order < 2:
            raise ValueError(f"current harmonic order must be >= 2, got {self.order}")


@dataclass(frozen=True)
class PhaseCircuit:
    """A motor phase as its current loop sees it: resistance and inductance."""

    resistance_ohm: float
    inductance_H: float

    def __post_init__(self) -> None:
        if self.resistance_ohm <= 0 or self.inductance_H <= 0:
            raise ValueError("a phase's resistance and inductance are positive")


@dataclass(frozen=True)
class AmplifierParams:
    """The drive's own imperfections, on top of whatever trims are written.

    The trims' offset adds to ``offset_*_mA`` (net offset = trim + amplifier
    offset); the gain error scales the sine/cosine reference (fundamental and
    distortion) but not the offset path. Bandwidths are those of a first-order
    current loop per phase; ``None`` is an ideal loop.

    ``pi_loop`` is the other form of ``current_loop_lag``: each loop a PI controller on
    the phase's R and L, tuned so that command to current is the first-order lag of its
    bandwidth (Kp = 2π·bandwidth·L, Ki = Kp·R/L), and the motor's back-EMF, its speed
    times ∂τ/∂i, a disturbance the loop rejects only within its bandwidth.

    ``dead_time_mA`` is the other form of ``current_distortion``: the bridge's dead time
    leaves each phase a current error of fixed size against the current's sign
    (i − D·tanh(i/knee)), the sign turning over ``dead_time_knee_mA``, about the PWM
    ripple's half-width. It distorts every odd order at once, and its share of the
    waveform falls as the current grows, where a harmonic waveform's holds its share.
    """

    offset_a_mA: float = 0.0
    offset_b_mA: float = 0.0
    gain_error_a: float = 0.0
    gain_error_b: float = 0.0
    distortion_a: tuple[CurrentHarmonic, ...] = ()
    distortion_b: tuple[CurrentHarmonic, ...] = ()
    bandwidth_a_hz: float | None = None
    bandwidth_b_hz: float | None = None
    dead_time_mA: float = 0.0
    dead_time_knee_mA: float = 20.0
    pi_loop: PhaseCircuit | None = None

    def __post_init__(self) -> None:
        if self.pi_loop is not None and self.bandwidth_a_hz is None:
            raise ValueError("PI current loops need their bandwidths")
        if self.dead_time_mA < 0 or self.dead_time_knee_mA <= 0:
            raise ValueError("a dead-time error is non-negative, and turns over a positive knee")
        for e in (self.gain_error_a, self.gain_error_b):
            if not -0.5 < e < 0.5:
                raise ValueError(f"amplifier gain error {e} is not a plausible fraction")
        if (self.bandwidth_a_hz is None) != (self.bandwidth_b_hz is None):
            raise ValueError("give both current-loop bandwidths or neither")
        for bw in (self.bandwidth_a_hz, self.bandwidth_b_hz):
            if bw is not None and bw <= 0:
                raise ValueError("current-loop bandwidth must be positive")


@dataclass(frozen=True)
class FrictionParams:
    """Coulomb (tanh-smoothed, direction dependent) plus viscous friction on one inertia.

    Torque opposing motion: ``viscous·ω + C(ω)·tanh(ω/smoothing)`` with
    C = coulomb_pos for ω ≥ 0, coulomb_neg otherwise (both magnitudes).
    """

    coulomb_pos_Nm: float
    coulomb_neg_Nm: float
    viscous_Nms: float
    smoothing_rad_s: float

    def __post_init__(self) -> None:
        if min(self.coulomb_pos_Nm, self.coulomb_neg_Nm, self.viscous_Nms) < 0:
            raise ValueError("friction coefficients are magnitudes (>= 0)")
        if self.smoothing_rad_s <= 0:
            raise ValueError("friction smoothing speed must be positive")


@dataclass(frozen=True)
class CouplingParams:
    """A compliant coupling between the rotor and the next inertia (``load_resonance``).

    ``resonance_hz`` fixes the coupling's stiffness: it is the frequency of
    the inertia right after the coupling oscillating on it with the rotor
    held, a property of the hardware that no current changes. (It is also the
    anti-resonance of the rotor's own response.) The modes of the whole chain
    mix it with the rotor's magnetic spring and so do move with the current;
    the truth lists them at rated current.
    """

    resonance_hz: float
    damping_ratio: float
    stiffness_Nm_per_rad: float
    damping_Nms_per_rad: float


@dataclass(frozen=True)
class DiskParams:
    """A rigid steel disk on the motor shaft (the paper's inertial load)."""

    inertia_kgm2: float


@dataclass(frozen=True)
class SecondModeParams:
    """Part of a belt's load on a compliance of its own beyond the belt (a camera head on a
    bracket, a carriage on a shaft): ``share`` of the load's inertia swings on it, and
    ``resonance_hz`` is that part's mode with the rest of the load held. Seen at the load
    shaft, like the belt's own stiffness."""

    share: float
    resonance_hz: float
    damping_ratio: float
    stiffness_Nm_per_rad: float
    damping_Nms_per_rad: float

    def __post_init__(self) -> None:
        if not 0.0 < self.share < 1.0:
            raise ValueError("the share of the load beyond a second compliance is in (0, 1)")


@dataclass(frozen=True)
class BeltParams:
    """The paper's pan unit: pinion, toothed belt (N_G = 1/7), heavy camera head.

    Stiffness and damping are those of the belt seen at the load shaft.
    """

    motor_pulley_inertia_kgm2: float
    load_inertia_kgm2: float
    stiffness_Nm_per_rad: float
    damping_Nms_per_rad: float
    reduction: float = BELT_REDUCTION
    second_mode: SecondModeParams | None = None


@dataclass(frozen=True)
class MechanicsParams:
    """What the rotor drives, and what always or optionally brakes it."""

    load: LoadKind
    rotor_bearing: FrictionParams
    disk: DiskParams | None = None
    belt: BeltParams | None = None
    load_bearing: FrictionParams | None = None
    load_friction: FrictionParams | None = None
    coupling: CouplingParams | None = None

    def __post_init__(self) -> None:
        if (self.load is LoadKind.DISK) != (self.disk is not None) or (
            self.load is LoadKind.BELT
        ) != (self.belt is not None):
            raise ValueError(f"mechanics for a {self.load} load need exactly its own parameters")

    @property
    def gear_ratio(self) -> float:
        """Load revolutions per motor revolution (ICD.md §5)."""
        return self.belt.reduction if self.belt is not None else 1.0


@dataclass(frozen=True)
class SensorParams:
    """The MEMS sensor on the load: range, bandwidth, noise, fixture geometry, clock.

    ``tilt_rad`` (``UnnamedEffect.SENSOR_TILT``) turns the element about the
    fixture's axial axis; ``nonlinearity_c2``/``_c3`` (``SENSOR_NONLINEARITY``)
    bend each axis's transfer to a + c2·a²/FS + c3·a³/FS², FS the full scale
    in m/s². Zero for a sensor mounted square with a linear element.
    """

    radius_m: float
    range_g: int = 2
    bandwidth_hz: float = 500.0
    damping_ratio: float = 1.0 / math.sqrt(2.0)
    noise_density_ug: float = 150.0
    bits: int = 16
    tangential_axis: Axis = Axis.X
    radial_axis: Axis = Axis.Y
    axial_axis: Axis = Axis.Z
    clock_drift_ppm: float = 0.0
    sample_phase: float = 0.0
    tilt_rad: float = 0.0
    nonlinearity_c2: float = 0.0
    nonlinearity_c3: float = 0.0

    def __post_init__(self) -> None:
        if self.range_g not in SENSOR_RANGES_G:
            raise ValueError(f"sensor range {self.range_g} g is not one of {SENSOR_RANGES_G}")
        if len({self.tangential_axis, self.radial_axis, self.axial_axis}) != 3:
            raise ValueError("tangential, radial and axial axes must differ")
        if self.radius_m <= 0 or self.bandwidth_hz <= 0 or self.noise_density_ug < 0:
            raise ValueError("radius and bandwidth must be positive, noise non-negative")
        if not 0.0 <= self.sample_phase < 1.0:
            raise ValueError("sample phase is a fraction of a sample period in [0, 1)")
        if not abs(self.tilt_rad) < math.pi / 4:
            raise ValueError("a sensor turned by 45° or more reads another axis, not a tilt")
        if abs(self.nonlinearity_c2) + abs(self.nonlinearity_c3) >= 0.5:
            raise ValueError("a nonlinearity of half the full scale is not a sensor")

    @property
    def unnamed_effects(self) -> frozenset[UnnamedEffect]:
        """The out-of-vocabulary imperfections this sensor's constants switch on."""
        present = set()
        if self.tilt_rad != 0.0:
            present.add(UnnamedEffect.SENSOR_TILT)
        if self.nonlinearity_c2 != 0.0 or self.nonlinearity_c3 != 0.0:
            present.add(UnnamedEffect.SENSOR_NONLINEARITY)
        return frozenset(present)

    def noise_sigma_mps2(self) -> float:
        """σ of one sample: density times √(noise bandwidth) of the 2nd-order low-pass.

        A 2nd-order low-pass ω0²/(s² + 2ζω0 s + ω0²) passes white noise as if it
        were a brick wall of π·f0/(4ζ) Hz.
        """
        enbw = math.pi * self.bandwidth_hz / (4.0 * self.damping_ratio)
        return self.noise_density_ug * 1e-6 * STANDARD_GRAVITY * math.sqrt(enbw)


@dataclass(frozen=True)
class UnitParams:
    """Everything that makes one simulated unit what it is (the "truth")."""

    serial: str
    serial_number: int
    motor: MotorParams
    amplifier: AmplifierParams
    mechanics: MechanicsParams
    sensor: SensorParams
    effects: frozenset[Effect] = frozenset()
    rated_current_mA: int = 1000
    microsteps: int = 256

    @property
    def rotor_teeth(self) -> int:
        return self.motor.rotor_teeth

    @property
    def load(self) -> LoadKind:
        return self.mechanics.load

    @property
    def gear_ratio(self) -> float:
        return self.mechanics.gear_ratio

    @property
    def sensor_radius_m(self) -> float:
        return self.sensor.radius_m

    @property
    def unnamed_effects(self) -> frozenset[UnnamedEffect]:
        """Physics on this unit that no vocabulary id describes (``UnnamedEffect``)."""
        return self.sensor.unnamed_effects


def as_jsonable(value: Any) -> Any:
    """Constants as JSON values, for a unit's truth file (``station.physics.truth``)."""
    if is_dataclass(value) and not isinstance(value, type):
        return {f.name: as_jsonable(getattr(value, f.name)) for f in fields(value)}
    if isinstance(value, Enum):
        return value.value
    if isinstance(value, tuple | list):
        return [as_jsonable(v) for v in value]
    if isinstance(value, frozenset | set):
        return sorted(as_jsonable(v) for v in value)
    if isinstance(value, float | int | str | bool) or value is None:
        return value
    raise TypeError(f"cannot express {type(value).__name__} in the truth file")


def _stream(label: str, group: str) -> np.random.Generator:
    """A Generator for one group of constants of one unit (SHA-256 of label and group)."""
    digest = hashlib.sha256(f"{label}/{group}".encode()).digest()
    return np.random.default_rng(np.random.SeedSequence(int.from_bytes(digest, "big")))


def _u(rng: np.random.Generator, low: float, high: float) -> float:
    return float(rng.uniform(low, high))


def _sign(rng: np.random.Generator) -> float:
    return 1.0 if rng.random() < 0.5 else -1.0


def _nominal_motor_speed_rad_s(rotor_teeth: int) -> float:
    return 2.0 * math.pi * NOMINAL_ELECTRICAL_HZ / rotor_teeth


def _draw_motor(label: str) -> MotorParams:
    rng = _stream(label, "motor")
    kt = _u(rng, 0.35, 0.45)
    field_current = 10.0
    nr = 50
    lm1 = kt / (field_current * nr)
    return MotorParams(
        rotor_teeth=nr,
        field_current_A=field_current,
        L0_H=_u(rng, 3.0e-3, 5.0e-3),
        Lm0_H=0.25 * lm1,
        Lm1_H=lm1,
        Lf0_H=0.05,
        rotor_inertia_kgm2=_u(rng, 5.0e-6, 8.0e-6),
    )


def _draw_flux(label: str, lm1: float) -> tuple[tuple[FluxHarmonic, ...], tuple[FluxHarmonic, ...]]:
    """j = 2..5 harmonics: common content, each phase a little different.

    Even orders put a 1st-harmonic torque on balanced currents (moving the
    offset null by several mA); the A/B difference of the 3rd moves the gain
    null by tens of units. Both are what left the paper's residual trims.
    """
    rng = _stream(label, f"effect/{Effect.FLUX_HARMONICS.value}")
    ratio_ranges = {2: (0.003, 0.01), 3: (0.003, 0.008), 4: (0.001, 0.004), 5: (0.001, 0.004)}
    phase_a: list[FluxHarmonic] = []
    phase_b: list[FluxHarmonic] = []
    for order, (low, high) in ratio_ranges.items():
        ratio = _u(rng, low, high)
        phase = _u(rng, 0.0, 2.0 * math.pi)
        for target in (phase_a, phase_b):
            target.append(FluxHarmonic(order, lm1 * ratio * _u(rng, 0.7, 1.3),
                                       phase + _u(rng, -0.3, 0.3)))
    return tuple(phase_a), tuple(phase_b)


def _draw_detent(label: str, motor: MotorParams, holding_Nm: float) -> tuple[DetentHarmonic, ...]:
    rng = _stream(label, f"effect/{Effect.DETENT_TORQUE.value}")
    nr, i_f = motor.rotor_teeth, motor.field_current_A
    peak4 = _u(rng, 0.01, 0.025) * holding_Nm
    peak8 = _u(rng, 0.1, 0.3) * peak4 * _sign(rng)
    # Peak of -½·Lfj·j·Nr·sin(j·Nr·θ)·i_f² is ½·j·Nr·Lfj·i_f².
    return (
        DetentHarmonic(4, peak4 / (0.5 * 4 * nr * i_f**2)),
        DetentHarmonic(8, peak8 / (0.5 * 8 * nr * i_f**2)),
    )


def _draw_reluctance(label: str, motor: MotorParams, rated_A: float) -> float:
    rng = _stream(label, f"effect/{Effect.RELUCTANCE_TORQUE.value}")
    fraction = _u(rng, 0.02, 0.05)
    # τ_vr peaks at Nr·L1·I²; make that a few % of the holding torque at rated current.
    return fraction * motor.kt_Nm_per_A * rated_A / (motor.rotor_teeth * rated_A**2)


def _draw_amplifier(label: str) -> AmplifierParams:
    rng = _stream(label, "amplifier")
    return AmplifierParams(
        offset_a_mA=_u(rng, -150.0, 150.0),
        offset_b_mA=_u(rng, -150.0, 150.0),
        gain_error_a=_u(rng, -0.08, 0.08),
        gain_error_b=_u(rng, -0.08, 0.08),
    )


def _draw_distortion(label: str) -> tuple[tuple[CurrentHarmonic, ...], tuple[CurrentHarmonic, ...]]:
    rng = _stream(label, f"effect/{Effect.CURRENT_DISTORTION.value}")
    ranges = {2: (0.005, 0.015), 3: (0.003, 0.01), 5: (0.002, 0.006)}
    phase_a: list[CurrentHarmonic] = []
    phase_b: list[CurrentHarmonic] = []
    for order, (low, high) in ranges.items():
        level = _u(rng, low, high)
        phase = _u(rng, 0.0, 2.0 * math.pi)
        for target in (phase_a, phase_b):
            target.append(CurrentHarmonic(order, level * _u(rng, 0.8, 1.2),
                                          phase + _u(rng, -0.3, 0.3)))
    return tuple(phase_a), tuple(phase_b)


def _draw_loop_bandwidths(label: str) -> tuple[float, float]:
    rng = _stream(label, f"effect/{Effect.CURRENT_LOOP_LAG.value}")
    common = _u(rng, 500.0, 3000.0)
    spread = _u(rng, 0.01, 0.05) * _sign(rng)
    return common * (1.0 + spread / 2.0), common * (1.0 - spread / 2.0)


def _draw_disk(label: str) -> DiskParams:
    return DiskParams(inertia_kgm2=_u(_stream(label, "disk"), 2.0e-5, 3.0e-5))


def _draw_belt(label: str, motor: MotorParams, rated_A: float) -> BeltParams:
    """Belt sized so the load-on-belt mode is at 7-10 Hz at rated current.

    With the rotor (plus pinion) on its magnetic spring K and the load on the
    belt k' (both seen at the motor), the 2-DOF eigenproblem gives for a
    wanted low eigenvalue λ: k' = λ·J_L'·(K − λ·J_m) / (K − λ·(J_L' + J_m)).
    The high mode then lands well above 150 Hz, so 20 Hz sits between them.
    """
    rng = _stream(label, "belt")
    pulley = _u(rng, 0.6e-5, 1.2e-5)
    load = _u(rng, 0.02, 0.04)
    f_low = _u(rng, 7.0, 10.0)
    zeta = _u(rng, 0.04, 0.08)
    n = BELT_REDUCTION
    j_m = motor.rotor_inertia_kgm2 + pulley
    j_l = load * n * n
    k_mag = motor.kt_Nm_per_A * rated_A * motor.rotor_teeth
    lam = (2.0 * math.pi * f_low) ** 2
    k_motor_side = lam * j_l * (k_mag - lam * j_m) / (k_mag - lam * (j_l + j_m))
    stiffness = k_motor_side / (n * n)
    return BeltParams(
        motor_pulley_inertia_kgm2=pulley,
        load_inertia_kgm2=load,
        stiffness_Nm_per_rad=stiffness,
        damping_Nms_per_rad=2.0 * zeta * math.sqrt(stiffness * load),
        reduction=n,
    )


def _draw_rotor_bearing(label: str, holding_Nm: float, rotor_teeth: int) -> FrictionParams:
    rng = _stream(label, "rotor-bearing")
    return FrictionParams(
        coulomb_pos_Nm=_u(rng, 0.003, 0.008) * holding_Nm,
        coulomb_neg_Nm=_u(rng, 0.003, 0.008) * holding_Nm,
        viscous_Nms=_u(rng, 0.002, 0.004),
        smoothing_rad_s=0.01 * _nominal_motor_speed_rad_s(rotor_teeth),
    )


def _draw_load_bearing(label: str, holding_load_Nm: float, load_speed: float) -> FrictionParams:
    rng = _stream(label, "load-bearing")
    coulomb = _u(rng, 0.01, 0.03) * holding_load_Nm
    return FrictionParams(
        coulomb_pos_Nm=coulomb,
        coulomb_neg_Nm=coulomb,
        viscous_Nms=_u(rng, 0.005, 0.02) * holding_load_Nm / load_speed,
        smoothing_rad_s=0.02 * load_speed,
    )


def _draw_load_friction(label: str, holding_load_Nm: float, load_speed: float) -> FrictionParams:
    """Friction at the load worth tens of % of the holding torque, direction dependent."""
    rng = _stream(label, f"effect/{Effect.FRICTION.value}")
    coulomb = _u(rng, 0.1, 0.3) * holding_load_Nm
    return FrictionParams(
        coulomb_pos_Nm=coulomb,
        coulomb_neg_Nm=coulomb * _u(rng, 0.7, 1.3),
        viscous_Nms=_u(rng, 0.02, 0.06) * holding_load_Nm / load_speed,
        smoothing_rad_s=0.02 * load_speed,
    )


def _draw_coupling(label: str, downstream_inertia: float) -> CouplingParams:
    rng = _stream(label, f"effect/{Effect.LOAD_RESONANCE.value}")
    f = _u(rng, 60.0, 250.0)
    zeta = _u(rng, 0.02, 0.05)
    k = (2.0 * math.pi * f) ** 2 * downstream_inertia
    return CouplingParams(
        resonance_hz=f,
        damping_ratio=zeta,
        stiffness_Nm_per_rad=k,
        damping_Nms_per_rad=2.0 * zeta * math.sqrt(k * downstream_inertia),
    )


SATURATION_DROP = (0.05, 0.20)
"""Torque constant at rated current below its low-current value (fraction)."""
ECCENTRICITY = (0.03, 0.10)
"""Airgap torque modulation once per revolution (fraction)."""
UNBALANCE = (0.001, 0.003)
"""The eccentric rotor's gravity load, as a fraction of the holding torque.

No more than the rotor bearing's Coulomb friction (and a real rotor's
unbalance is smaller still): a disabled rotor then creeps towards its low
point instead of swinging there, which the sensor would see at standstill.
Bearings without a Coulomb part (the wide population's) hold nothing, so the
plant starts every rotor at rest where it settled (``motor.rest_angle``).
"""


def draw_saturation(rng: np.random.Generator, rated_A: float) -> float:
    """I_s for a torque constant 5-20 % low at rated current."""
    return saturation_current_for_drop(rated_A, _u(rng, *SATURATION_DROP))


def draw_eccentricity(rng: np.random.Generator, holding_Nm: float) -> Eccentricity:
    """Eccentricity 3-10 %, anywhere round the rotor, and the unbalance that comes with it."""
    return Eccentricity(
        relative=_u(rng, *ECCENTRICITY),
        phase_rad=_u(rng, 0.0, 2.0 * math.pi),
        unbalance_Nm=_u(rng, *UNBALANCE) * holding_Nm,
        unbalance_phase_rad=_u(rng, 0.0, 2.0 * math.pi),
    )


def _draw_clock(label: str) -> tuple[float, float]:
    rng = _stream(label, f"effect/{Effect.SENSOR_CLOCK_DRIFT.value}")
    return _u(rng, 100.0, 500.0) * _sign(rng), _u(rng, 0.0, 1.0)


def _concealed_effects(label: str) -> frozenset[Effect]:
    rng = _stream(label, "effects")
    return frozenset(e for e in Effect if rng.random() < EFFECT_PROBABILITY)


@dataclass(frozen=True)
class DrawnEffects:
    """A unit's magnitudes of every motor and amplifier effect, drawn whether on or not.

    Drawing them all keeps a unit the same unit whichever effects are switched on:
    its twin without an effect differs in that effect alone.
    """

    L1_H: float
    flux_a: tuple[FluxHarmonic, ...]
    flux_b: tuple[FluxHarmonic, ...]
    detent: tuple[DetentHarmonic, ...]
    saturation_current_A: float
    eccentricity: Eccentricity
    distortion_a: tuple[CurrentHarmonic, ...]
    distortion_b: tuple[CurrentHarmonic, ...]
    bandwidth_a_hz: float
    bandwidth_b_hz: float

    def switched(self, motor: MotorParams, amplifier: AmplifierParams,
                 on: frozenset[Effect]) -> tuple[MotorParams, AmplifierParams]:
        """``motor`` and ``amplifier`` with exactly the effects in ``on``."""
        lag = Effect.CURRENT_LOOP_LAG in on
        distort = Effect.CURRENT_DISTORTION in on
        flux = Effect.FLUX_HARMONICS in on
        return replace(
            motor,
            L1_H=self.L1_H if Effect.RELUCTANCE_TORQUE in on else 0.0,
            flux_a=self.flux_a if flux else (),
            flux_b=self.flux_b if flux else (),
            detent=self.detent if Effect.DETENT_TORQUE in on else (),
            saturation_current_A=(self.saturation_current_A
                                  if Effect.MAGNETIC_SATURATION in on else None),
            eccentricity=self.eccentricity if Effect.ROTOR_ECCENTRICITY in on else None,
        ), replace(
            amplifier,
            distortion_a=self.distortion_a if distort else (),
            distortion_b=self.distortion_b if distort else (),
            bandwidth_a_hz=self.bandwidth_a_hz if lag else None,
            bandwidth_b_hz=self.bandwidth_b_hz if lag else None,
        )


def derive_unit(
    serial: str,
    *,
    load: LoadKind = LoadKind.DISK,
    effects: Iterable[Effect] | None = None,
    noise_density_ug: float | None = None,
) -> UnitParams:
    """The simulated unit behind a serial label, always the same for the same label.

    ``effects=None`` gives the unit its own concealed effects (drawn from the
    serial); otherwise exactly the given ones, with the magnitudes this unit
    would have had.
    """
    parsed = parse_serial(serial)
    label = parsed.label
    chosen = _concealed_effects(label) if effects is None else frozenset(Effect(e) for e in effects)
    rated_mA = 1000
    rated_A = rated_mA / 1000.0

    motor = _draw_motor(label)
    holding = motor.holding_torque_Nm(rated_A)
    flux_a, flux_b = _draw_flux(label, motor.Lm1_H)
    detent = _draw_detent(label, motor, holding)
    l1 = _draw_reluctance(label, motor, rated_A)
    saturation = draw_saturation(_stream(label, f"effect/{Effect.MAGNETIC_SATURATION.value}"),
                                 rated_A)
    eccentricity = draw_eccentricity(
        _stream(label, f"effect/{Effect.ROTOR_ECCENTRICITY.value}"), holding)
    amp = _draw_amplifier(label)
    dist_a, dist_b = _draw_distortion(label)
    bw_a, bw_b = _draw_loop_bandwidths(label)
    drawn = DrawnEffects(l1, flux_a, flux_b, detent, saturation, eccentricity,
                         dist_a, dist_b, bw_a, bw_b)
    motor, amplifier = drawn.switched(motor, amp, chosen)

    disk = _draw_disk(label)
    belt = _draw_belt(label, motor, rated_A)
    motor_speed = _nominal_motor_speed_rad_s(motor.rotor_teeth)
    ratio = belt.reduction if load is LoadKind.BELT else 1.0
    holding_load = holding / ratio
    load_speed = motor_speed * ratio
    rotor_bearing = _draw_rotor_bearing(label, holding, motor.rotor_teeth)
    load_bearing = _draw_load_bearing(label, holding_load, load_speed)
    load_friction = _draw_load_friction(label, holding_load, load_speed)
    downstream = disk.inertia_kgm2 if load is LoadKind.DISK else belt.motor_pulley_inertia_kgm2
    coupling = _draw_coupling(label, downstream)
    mechanics = MechanicsParams(
        load=load,
        rotor_bearing=rotor_bearing,
        disk=disk if load is LoadKind.DISK else None,
        belt=belt if load is LoadKind.BELT else None,
        load_bearing=load_bearing if load is LoadKind.BELT else None,
        load_friction=load_friction if Effect.FRICTION in chosen else None,
        coupling=coupling if Effect.LOAD_RESONANCE in chosen else None,
    )

    sensor_rng = _stream(label, "sensor")
    density = _u(sensor_rng, 100.0, 200.0)
    drift_ppm, sample_phase = _draw_clock(label)
    drift = Effect.SENSOR_CLOCK_DRIFT in chosen
    sensor = SensorParams(
        radius_m=0.04 if load is LoadKind.DISK else 0.10,
        noise_density_ug=density if noise_density_ug is None else float(noise_density_ug),
        clock_drift_ppm=drift_ppm if drift else 0.0,
        sample_phase=sample_phase if drift else 0.0,
    )
    return UnitParams(
        serial=label,
        serial_number=parsed.number,
        motor=motor,
        amplifier=amplifier,
        mechanics=mechanics,
        sensor=sensor,
        effects=chosen,
        rated_current_mA=rated_mA,
        microsteps=256,
    )
