"""The trims a perfect calibration would find, computed from the plant itself.

The truth a calibration is judged against must include everything the unit
does, effects and nonlinearity alike, so it comes from noise-free steady-state
runs of the same plant the simulated bench uses, not from eq. (16). What the
paper's procedure nulls is the 1st harmonic of the load's tangential
acceleration (through the offsets) and the 2nd (through the gain split at a
constant gain sum). Near the optimum both are close to affine in the trims, so
a Newton iteration on finite differences converges in a few runs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from station.core import GAIN_LIMITS, GAIN_UNITY, Trims, offset_limit_mA
from station.dsp import h1_then_h2_null, harmonic_phasors
from station.physics.params import UnitParams
from station.physics.plant import DriveCommand, Plant, modal_analysis

OFFSET_STEP_mA = 20.0
"""Finite-difference step for the offsets: large against rounding, small against curvature."""

SPLIT_STEP = 200.0
"""Finite-difference step for the gain split (1/10000)."""

DEFAULT_STEPS = np.array([OFFSET_STEP_mA, OFFSET_STEP_mA, SPLIT_STEP])
SMALLEST_STEPS = np.array([1.0, 1.0, 10.0])
"""Near the optimum the differences shrink with the steps, down to these: still far above
the steady harmonics' rounding."""

TOLERANCE_mA = 0.01
TOLERANCE_GAIN = 0.1
MAX_ITERATIONS = 12

_SETTLE_DECAY = math.log(1e3)
"""Transients are let decay by this many e-foldings of the slowest mode before measuring."""
_MIN_SETTLE_S = 0.2
_MAX_EXTRA_PERIODS = 50
_MAX_SETTLE_S = 5.0


def _quiet(unit: UnitParams) -> UnitParams:
    """The same unit with a perfect sensor (no noise, sampling on the SYNC): truth, not a
    measurement.

    A drifting sample clock is the sensor's, not the plant's: sampled late on a
    unit whose flux harmonics put 16 m/s² rms into orders 4-12, one repeated
    sample per wrap leaked into orders 1 and 2 of a four-period window and moved
    the optimum 43 mA away from the plant's own (population seed 335014438).
    """
    return replace(unit, sensor=replace(unit.sensor, noise_density_ug=0.0, clock_drift_ppm=0.0))


def settle_time_s(unit: UnitParams, amplitude_mA: float) -> float:
    """How long the slowest mode needs to forget a start on the steady trajectory."""
    rates = [m.decay_rate_per_s for m in modal_analysis(unit, amplitude_mA)]
    slowest = min((r for r in rates if r > 0), default=1.0 / _MAX_SETTLE_S)
    return min(_MAX_SETTLE_S, max(_MIN_SETTLE_S, _SETTLE_DECAY / slowest))


def steady_harmonics(
    unit: UnitParams,
    trims: Trims,
    *,
    amplitude_mA: float = 1000.0,
    electrical_hz: float = 20.0,
    sync_period_s: float = 0.001,
    orders: Sequence[int] = (1, 2),
    periods: int | None = None,
    substeps: int = 8,
) -> NDArray[np.complex128]:
    """Steady-state harmonics of the sensor's tangential reading (m/s², noise-free).

    Phasors per ``harmonic_phasors``, referenced to the drive's electrical
    angle x_u at each SYNC, over ``periods`` whole electrical periods after
    the transients have died out. This is what a perfect station would
    demodulate at constant speed with these trims.

    By default over four periods, or over a whole mechanical revolution where the
    rotor is eccentric (``revolution_periods``).
    """
    acc, angle = steady_reading(unit, trims, amplitude_mA=amplitude_mA,
                                electrical_hz=electrical_hz, sync_period_s=sync_period_s,
                                periods=periods, substeps=substeps)
    return harmonic_phasors(acc[:, unit.sensor.tangential_axis.column], angle, orders)


STEADY_PERIODS = 4
"""Electrical periods a steady state is measured over where one period is like the next."""


def revolution_periods(unit: UnitParams) -> int:
    """The periods over which a steady state repeats: one, except for an eccentric rotor.

    Its airgap, and its unbalance, turn with the rotor: the torque ripple of every
    order is modulated once per revolution, and over a short window the sidebands at
    f ± f_rotor are part of each harmonic, by the rotor's angle. A development disk
    read H1 0.018 to 0.197 m/s² at one set of trims depending on where its rotor was,
    and its "optimum" over four periods at one angle lay 13 mA from the null of what
    the trims can change (seed 1136781479). Over a whole revolution the sidebands
    average out: what is left is the part no rotor angle changes, the only part the
    trims can null, and what the station's maps (with their rotor term) estimate.
    """
    if unit.motor.eccentricity is None:
        return STEADY_PERIODS
    return unit.rotor_teeth


def steady_reading(
    unit: UnitParams,
    trims: Trims,
    *,
    amplitude_mA: float = 1000.0,
    electrical_hz: float = 20.0,
    sync_period_s: float = 0.001,
    periods: int | None = None,
    substeps: int = 8,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The sensor's steady reading, (samples, 3) in m/s² without noise or range, and the
    drive's electrical angle at each sample: what every SYNC would give over ``periods``
    whole periods once the transients have died out (by default as ``steady_harmonics``)."""
    if periods is None:
        periods = revolution_periods(unit)
    if electrical_hz <= 0 or periods < 1:
        raise ValueError("need a positive electrical frequency and at least one period")
    plant = Plant(_quiet(unit), sync_period_s=sync_period_s, substeps=substeps)
    m = unit.microsteps
    velocity = electrical_hz * 4.0 * m
    samples_per_period = 1.0 / (electrical_hz * sync_period_s)
    measured = _whole_period_samples(samples_per_period, periods)
    settle = math.ceil(settle_time_s(unit, amplitude_mA) / sync_period_s)
    plant.place_on_trajectory(
        DriveCommand(True, amplitude_mA, trims, 0.0, velocity, 0.0, m)
    )
    acc: NDArray[np.float64] = np.empty((measured, 3))
    for n in range(settle + measured):
        plant.advance(DriveCommand(True, amplitude_mA, trims, velocity * n * sync_period_s,
                                   velocity, 0.0, m))
        if n >= settle:
            acc[n - settle] = plant.sensor_reading_mps2
    ends = np.arange(settle + 1, settle + measured + 1, dtype=np.float64)
    angle: NDArray[np.float64] = 2.0 * math.pi * ends * sync_period_s * velocity / (4.0 * m)
    return acc, angle


def _whole_period_samples(samples_per_period: float, periods: int) -> int:
    """The fewest samples, for at least ``periods`` periods, that span whole periods.

    Demodulation rejects the other orders only over whole periods: at 1 kHz,
    30 Hz fits whole samples every 3 periods, so 4 asked become 6 (200
    samples), not 133.3. Frequencies with no short common period with the SYNC
    rate fall back to the nearest count.
    """
    for count in range(periods, periods + _MAX_EXTRA_PERIODS):
        samples = count * samples_per_period
        if abs(samples - round(samples)) < 1e-6:
            return round(samples)
    return max(1, round(periods * samples_per_period))


def _trims(u: NDArray[np.float64]) -> Trims:
    return Trims(float(u[0]), float(u[1]), GAIN_UNITY + float(u[2]), GAIN_UNITY - float(u[2]))


def amplifier_optimum(unit: UnitParams) -> Trims:
    """Where eq. (16) puts the optimum for the amplifier's errors alone: no net offset,
    equal actual fundamentals at a constant gain sum."""
    amp = unit.amplifier
    gain_a = 2 * GAIN_UNITY * (1 + amp.gain_error_b) / (2 + amp.gain_error_a + amp.gain_error_b)
    return Trims(-amp.offset_a_mA, -amp.offset_b_mA, gain_a, 2 * GAIN_UNITY - gain_a)


def optimal_trims(
    unit: UnitParams,
    *,
    amplitude_mA: float = 1000.0,
    electrical_hz: float = 20.0,
    sync_period_s: float = 0.001,
) -> Trims:
    """Trims that null H1 and minimise |H2| over the split gain_a + gain_b = 20000.

    Newton on finite differences (steps of 20 mA and 200 gain units, shrinking with
    the iteration's own steps) from the optimum of the amplifier's errors alone, within
    the trims the drive can hold, keeping the Jacobian while it converges (chord steps)
    near where it was taken, and refreshing it otherwise.
    """

    def harmonics(u: NDArray[np.float64]) -> tuple[complex, complex]:
        h = steady_harmonics(unit, _trims(u), amplitude_mA=amplitude_mA,
                             electrical_hz=electrical_hz, sync_period_s=sync_period_s)
        return complex(h[0]), complex(h[1])

    def jacobian(u: NDArray[np.float64], base: tuple[complex, complex],
                 steps: NDArray[np.float64] = DEFAULT_STEPS) -> tuple[
            NDArray[np.complex128], NDArray[np.complex128]]:
        jac1 = np.empty(3, dtype=np.complex128)
        jac2 = np.empty(3, dtype=np.complex128)
        for i, step in enumerate(steps.tolist()):
            probe = u.copy()
            probe[i] += step
            p1, p2 = harmonics(probe)
            jac1[i] = (p1 - base[0]) / step
            jac2[i] = (p2 - base[1]) / step
        return jac1, jac2

    if amplitude_mA <= 0:
        raise ValueError("the optimum is defined for a positive phase current amplitude")
    # From where the amplifier's own errors put the optimum; the other effects move it
    # from there, and Newton follows. From the nominal trims a unit whose phases differ by
    # a quarter was first sent 14,000 gain units the wrong way (population seed 956725264).
    start = amplifier_optimum(unit)
    u = np.array([start.offset_a_mA, start.offset_b_mA, (start.gain_a - start.gain_b) / 2.0])
    base = harmonics(u)
    jac1, jac2 = jacobian(u, base)
    previous = math.inf
    # Where the drive can hold trims at all (ICD.md §2): a step the affine model takes
    # beyond it lands the plant in nonsense (population seed 956725264: a first step of
    # 14,000 gain units, to gain −4,560, and no way back).
    reach = offset_limit_mA(unit.rated_current_mA)
    room = min(GAIN_UNITY - GAIN_LIMITS[0], GAIN_LIMITS[1] - GAIN_UNITY)
    low, high = np.array([-reach, -reach, -room]), np.array([reach, reach, room])
    for _ in range(MAX_ITERATIONS):
        delta = np.clip(u + h1_then_h2_null(base[0], base[1], jac1, jac2), low, high) - u
        u = u + delta
        size = max(abs(delta[0]) / TOLERANCE_mA, abs(delta[1]) / TOLERANCE_mA,
                   abs(delta[2]) / TOLERANCE_GAIN)
        if size <= 1.0:
            return _trims(u)
        base = harmonics(u)
        # A chord step is kept only near where its Jacobian was taken: when Newton started
        # at the nominal trims a rough unit's first step spanned 200 mA and 1,000 gain
        # units, and the chord then alternated about its optimum shrinking by half a step
        # each time (population seed 170: 14 iterations where 12 were allowed).
        far = bool(np.any(np.abs(delta) > DEFAULT_STEPS))
        if far or size > 0.5 * previous:
            # Differences on the scale the iteration now moves at: a rough unit's H2 can
            # curve within the default steps, and their slope then overshot the optimum
            # twice over, in a cycle that never closed (population seed 576: detent, flux,
            # reluctance and a lagging loop).
            jac1, jac2 = jacobian(u, base, np.clip(np.abs(delta), SMALLEST_STEPS, DEFAULT_STEPS))
        previous = size
    # A truth that is not converged would silently mislead every comparison with it.
    raise RuntimeError(f"optimal trims for {unit.serial} did not converge: last {_trims(u)}")
