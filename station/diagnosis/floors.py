"""How far the model itself is trusted, and the magnetic spring its motion rides.

A residual is judged against the measurement's noise and against what the model cannot
know to better than a fraction: each order's torque balance as the chain magnifies it,
and a bearing's friction where what it acts on nearly stops (``floor``). The spring the
swing rides (``swing_springs``) is what a transient rings on.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from station.diagnosis import chain
from station.diagnosis.effects import friction
from station.diagnosis.effects.friction import FLOOR_SMOOTHING, FRICTION_TURN_SHARE, cell_means
from station.diagnosis.layout import ChainKind
from station.diagnosis.motion import Motion
from station.diagnosis.observations import MODEL_FLOOR

if TYPE_CHECKING:
    from station.diagnosis.model import Model


def floor(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """What the model itself is trusted to, per segment and order, m/s²: every order's
    torque balance to ``MODEL_FLOOR`` as the chain magnifies it (``magnification``),
    and the bearings' friction where what it acts on nearly stops
    (``turning_floor``)."""
    magnified = MODEL_FLOOR * np.abs(model.obs.phasors) * magnification(model, p)
    out: NDArray[np.float64] = np.hypot(magnified, turning_floor(model, p))
    return out


def turning_floor(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
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
    x = model.inputs(p)
    step = model.made_and_step(p)[1]
    level = float(np.mean(model.block(p, "friction_coulomb")))

    def harmonics(velocity: NDArray[np.float64], torque: float,
                  through: NDArray[np.complex128] | float = 1.0) -> NDArray[np.float64]:
        eps = FLOOR_SMOOTHING * float(np.min(np.abs(velocity.mean(axis=1))))
        sign = cell_means(velocity, eps)[0]
        made = through * model.analysed_cells(torque * sign)
        return np.abs(step.apply(made)) / model.weight

    # At the load its friction enters through the chain (``error``: t.d·F); at the
    # rotor, as the motor's torque itself.
    load = harmonics(friction.load_velocity(model, p), level, x.transfer.d)
    out: NDArray[np.float64] = FRICTION_TURN_SHARE * load
    if model.spec.chain is ChainKind.BELT:
        theta = x.transfer.a * x.alpha + x.transfer.b * x.friction  # rotor angle, mech rad
        speed = model.obs.omega[:, None] / model.rotor_teeth
        rotor = speed + ((model.jw * theta) @ model.synth).real
        out = np.hypot(out, harmonics(rotor, model.gear_ratio * level))
    return out


def magnification(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
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
    m = model.motion(p)
    k = model.obs.orders
    theta, need = chain.chain_response(model, m)
    stiff = segment_springs(model, p, m)[:, None]
    size = (np.abs(stiff * theta) + np.abs(need)) * np.abs(m.alpha)  # each balance, (S, K)
    inverse = model.made_and_step(p)[1].inverse
    # Re and Im of each order's error independent, each with half the variance.
    spread = 0.5 * np.concatenate([size, size], axis=1) ** 2
    variance = np.einsum("sij,sj->si", inverse * inverse, spread)
    coupled = np.sqrt(variance[:, :k] + variance[:, k:])
    moving = np.maximum(np.abs(m.alpha), 1e-12 * max(float(np.max(np.abs(m.alpha))), 1e-300))
    out: NDArray[np.float64] = np.maximum(coupled / moving, 1.0)
    return out


def segment_springs(model: Model, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
    """Each segment's magnetic spring along its motion (Kt units per mechanical rad):
    the torque's restoring slope averaged over the grid."""
    out: NDArray[np.float64] = -np.mean(model.torque_slope(p, m), axis=1) * model.rotor_teeth
    return out


def swing_springs(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
    """The magnetic spring per condition as the rotor's swing rides it (Kt units per
    mechanical rad): the torque's slope averaged over the grid and the segments.

    A transient rings on the spring the motion averages, not on the static one: a
    rough development disk (none@208) swinging up to ±0.5 electrical rad rides 0.94-0.96
    of its static spring, and its mode sits 2-3 % below the one ``modes`` gives at rest.
    """
    slope = segment_springs(model, p, model.motion(p))
    count = len(model.obs.conditions)
    total = np.bincount(model.obs.condition, weights=slope, minlength=count)
    seen = np.bincount(model.obs.condition, minlength=count)
    out: NDArray[np.float64] = total / np.maximum(seen, 1)
    return out
