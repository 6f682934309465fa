"""Friction: the bearings' and the load's, a torque against the motion.

Every motor's bearings have some: Coulomb friction up to 10 % of the rated holding torque
in either direction and viscous drag are a healthy unit's (CLI.md), so the nominal model
carries them (``nominal_blocks``) under a guarded ceiling and never names them. The id
frees the ceiling: it names friction beyond a healthy unit's, and adds no block of its
own, so it counts as one parameter in every test (``name.compare``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms, Params, Starts
from station.diagnosis.effects.readings import sigmas
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.observations import Observations

FRICTION_SMOOTHING_MAX = 0.1
"""Coulomb friction's smoothing, at most this fraction of the slowest mean load speed.

Coulomb friction is a torque that does not change with speed once the load moves. At this
ceiling its smoothed sign has settled at every hold (tanh 10), so the smoothing (the
nominal model's since issue 90, the group's before) cannot make a drag that grows with
speed and damps the ripple at low speeds, which any chain the
nominal model got slightly wrong could use (a clean belt unit was named friction at
0.8 % of holding torque, smoothed over half its top speed). Below it the smoothing shows
only where the load's swing nearly stops it; where it never does, the data do not fix
it, and a fit resting on the ceiling is friction like any other (a belt with Coulomb
friction of 19 % of its holding torque fitted the ceiling and explained 6370 of the
nominal's held-out χ² of 8546)."""


HEALTHY_COULOMB = 0.10
"""CLI.md's healthy unit: Coulomb friction up to this share of the rated holding torque
(Kt × rated current) at the motor shaft, in either direction, as every motor's bearings
have. The nominal model fits it and never names it."""

HEALTHY_COULOMB_GUARD = 1.2
"""The nominal model's ceiling on each direction's Coulomb level, relative to
``HEALTHY_COULOMB``: a gauge's guard band. The levels are read from the load angles to
about 0.1 % of the holding torque on the station's own recordings (a disk control with 6
and 4 % forward and reverse read 6.14 ± 0.09 and 4.02 ± 0.09), but the torque scale rests
on the drive's current calibration and on the model's own floor (``MODEL_FLOOR``), so a
healthy unit at the limit must not be named for reading a little above it. Friction from
1.5 times the limit clears the ceiling by tens of σ of the torque balance."""

FRICTION_TURN_SHARE = 0.3
"""How far the friction's harmonics are trusted where the load nearly stops (``floors.floor``):
to about a third, the spread between the common laws of friction at a reversal."""

FLOOR_SMOOTHING = 0.05
"""Of the slowest mean speed: the speed over which the friction of ``floors.turning_floor``
turns, whatever the fit's own smoothing."""

FRICTION_CEILING = 5.0
"""Each direction's Coulomb level (Kt units, at the load) once the ``friction`` group
releases the healthy ceiling: five times the torque of an ampere, more than any motor on
the fixture could turn against."""

FRICTION_SMOOTHING_START = 0.02
"""Where the nominal model starts Coulomb friction's smoothing, relative to the slowest mean
load speed. How sharply a bearing's friction turns is part of the healthy unit, fitted and
never named: where the load never nears stopping the data say nothing of it (its column is
zero to the bit, and it stays where it starts); where the load nearly stops, what the fit
finds says as much about how well the velocity near zero is measured as about the bearing.
Held fixed, it named healthy units ``friction`` for their smoothing alone, whatever it was
fixed at: at 2 % of the slowest speed a disk characterized down to 5.5 Hz (none@41143823,
bearings' Coulomb 8.6 and 1.8 %), at the bearing's own 0.025 rad/s another (none@502, 9.9
and 4.2 %, fitted at 4.6 %: held-out χ² 1,907 → 1,768)."""


def healthy_coulomb_ceiling(obs: Observations) -> float:
    """The nominal model's ceiling on each Coulomb level, in Kt units at the load: seen at
    the motor a load torque is ·n, and the holding torque in Kt units is the rated current."""
    rated_A = obs.metadata.rated_current_mA / 1000.0
    return HEALTHY_COULOMB * HEALTHY_COULOMB_GUARD * rated_A / obs.metadata.gear_ratio


def nominal_blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    """Every motor's bearings: Coulomb friction forward and reverse (Kt units, at the load),
    never negative, capped at the healthy level unless the id is on; and how sharply it
    turns. The viscous part is the chain's damping."""
    ceiling = (FRICTION_CEILING if Effect.FRICTION in spec.effects
               else healthy_coulomb_ceiling(obs))
    return [Block("friction_coulomb", 2, 0.0, 0.0, ceiling, BlockKind.LINEAR),
            Block("log_friction_smoothing", 1, math.log(FRICTION_SMOOTHING_START),
                  math.log(1e-4), math.log(FRICTION_SMOOTHING_MAX))]


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    # The levels and their smoothing are the nominal's (``nominal_blocks``).
    return []


START_SMOOTHING = (0.005, 0.02, 0.08)
"""How sharply the friction turns, relative to the slowest mean load speed, where a search
starts."""


def starts(model: Model, p: Params) -> list[Starts]:
    return [{"log_friction_smoothing": [math.log(eps)]} for eps in START_SMOOTHING]


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["friction_coulomb"]
    v, s = fit.params[sl], sigmas(cov)[sl]
    rated = fit.model.rated_A
    ratio = fit.model.gear_ratio
    # Coulomb levels are load torques in Kt units; seen at the motor they are ·n.
    scale = 100.0 * ratio / rated
    return {
        "coulomb_forward_percent_of_rated_holding_torque": float(v[0]) * scale,
        "coulomb_forward_sigma_percent": float(s[0]) * scale,
        "coulomb_reverse_percent_of_rated_holding_torque": float(v[1]) * scale,
        "coulomb_reverse_sigma_percent": float(s[1]) * scale,
        "smoothing_relative_to_slowest_speed": math.exp(fit.scalar("log_friction_smoothing")),
        "healthy_coulomb_limit_percent": 100.0 * HEALTHY_COULOMB,
        "note": ("the whole Coulomb levels, the bearings' healthy share among them; viscous "
                 "friction is in the chain's damping (nominal)"),
    }


# ---------------------------------------------------------------- the law, on the grid
_BAND = 3
"""A step's mean depends on its own grid point's velocity and its two neighbours'."""


SETTLED_SCALE = 20.0
"""|v|/ε beyond which the smoothed sign is ±1 to the last bit: tanh rounds to 1 from 19.1,
and what a step's secant adds (about 4·e^{−2|v|/ε}) is below half an ulp of 1 from 18.8."""


def cell_means(v: NDArray[np.float64], eps: float) -> tuple[NDArray[np.float64], ...]:
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
        return cell_means_made(v, eps)
    mean_t = np.zeros_like(rows)
    mean_t[forward], mean_t[reverse] = 1.0, -1.0
    mean_t2 = np.ones_like(rows)
    band_t = np.zeros((rows.shape[0], _BAND, n))
    band_t2 = np.zeros_like(band_t)
    if moving.any():
        mean_t[moving], mean_t2[moving], band_t[moving], band_t2[moving] = cell_means_made(
            rows[moving], eps)
    lead = v.shape[:-1]
    return (mean_t.reshape(v.shape), mean_t2.reshape(v.shape),
            band_t.reshape(*lead, _BAND, n), band_t2.reshape(*lead, _BAND, n))


def cell_means_made(v: NDArray[np.float64], eps: float) -> tuple[NDArray[np.float64], ...]:
    """``cell_means`` made in full on every row.

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


def friction_torque(model: Model, p: NDArray[np.float64]
                    ) -> tuple[NDArray[np.complex128], NDArray[np.float64],
                               NDArray[np.float64]]:
    """Friction on the load evaluated on its measured velocity: per-order torque (S, K),
    how each step's friction moves with the velocity at its three grid points
    (S, 3, N: ``friction_response``), and mean torque (S,)."""
    shapes = model.friction_shapes_here(p)
    c = model.block(p, "friction_coulomb")
    force = c[0] * shapes[0] + c[1] * shapes[1]
    slope = c[0] * shapes[2] + c[1] * shapes[3]  # (S, 3, N)
    # The load's viscous part is in the chain already, as the load stage's damping.
    return model.analysed_cells(force), slope, force.mean(axis=1)


def load_velocity(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """The load's angular velocity on the grid: its mean plus the measured ripple, the
    orders above K included as in the rotor's swing.

    Where a rough ripple nearly stops the load, those orders decide when friction
    turns. Without them, development trial friction+sensor_clock_drift@101 (a disk)
    left 24,372 of held-out χ² with both groups fitted; with them 6,239 (nominal
    542,113 for 1,752 values), and the diagnosis names the clock beside friction.
    """
    _, alpha, above = model.load_motion(p)
    ripple = ((alpha / model.jw) @ model.synth).real
    if above is not None:
        ripple = ripple + ((above / model.jw_beyond) @ model.synth_beyond).real
    out: NDArray[np.float64] = model.load_speed + ripple
    return out


def friction_shapes(model: Model, p: NDArray[np.float64], velocity: NDArray[np.float64]
                    ) -> tuple[NDArray[np.float64], ...]:
    """Coulomb friction per unit of its forward and reverse levels, and their slopes.

    A smoothed sign, tanh(v/ε), splits into a forward part (1 + tanh)/2 and a
    reverse part (1 − tanh)/2 so the two directions may differ; ε is relative to
    the slowest mean load speed of the recording (``FRICTION_SMOOTHING_MAX``).

    Each grid value is the shape's mean over its grid step, the velocity taken as
    straight between grid points (``cell_means``), not its value at the point.
    Where ε is far below the velocity's change over a step (a load whose swing
    stops it), a point value is a sampled jump: it moved only when a point crossed
    zero, and the mean slope, sech² at 48 points, swung between nothing and 1/ε as a
    point fell near the crossing. On development friction @1850757460 (the load
    reversing in one segment of 88) a sensor delay 0.01 ms longer moved that
    segment's χ² from 47 to 86,219, and every estimate held out beside it with it.
    """
    scale = float(np.min(np.abs(model.obs.load_speed)))
    eps = math.exp(model.scalar(p, "log_friction_smoothing")) * scale
    mean_t, mean_t2, slope_t, slope_t2 = cell_means(velocity, eps)
    fwd = 0.5 * (mean_t + mean_t2)
    rev = 0.5 * (mean_t - mean_t2)
    return fwd, rev, 0.5 * (slope_t + slope_t2), 0.5 * (slope_t - slope_t2)


def friction_response(model: Model, slope: NDArray[np.float64], x: NDArray[np.complex128]
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
    # Segments whose load never nears a stop have no slope (``cell_means``): nothing
    # moves there, and only the others are made.
    live = np.any(slope, axis=(-2, -1))
    live = live.reshape(-1, live.shape[-1]).any(axis=0)  # (S,)
    if live.all():
        return friction_response_on(model, slope, x, model.jw)
    out = np.zeros((*np.broadcast_shapes(x.shape[:-2], slope.shape[:-3]), *model.jw.shape),
                   dtype=np.complex128)
    if live.any():
        x_live = x if x.shape[-2] == 1 else x[..., live, :]
        out[..., live, :] = friction_response_on(model, slope[..., live, :, :], x_live,
                                                 model.jw[live])
    return out


def friction_response_on(model: Model, slope: NDArray[np.float64], x: NDArray[np.complex128],
                 jw: NDArray[np.complex128]) -> NDArray[np.complex128]:
    """``friction_response`` on the segments ``jw`` belongs to."""
    dv = ((x / jw) @ model.synth).real  # (…, S, N)
    moved = (slope[..., 0, :] * np.roll(dv, 1, axis=-1) + slope[..., 1, :] * dv
             + slope[..., 2, :] * np.roll(dv, -1, axis=-1))
    return model.analysed_cells(moved)


TERMS = EffectTerms(
    effect=Effect.FRICTION,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Kept by the nominal model: every motor's bearings have Coulomb friction (CLI.md: up "
        "to 10 % of the rated holding torque, either direction) and viscous drag, fitted "
        "and reported with σ under nominal.friction. Named only past a guarded ceiling "
        "(HEALTHY_COULOMB_GUARD) or as another form."),
    nominal_blocks=nominal_blocks,
    starts=starts,
)
