"""The model's derivatives from its structure: the linear parameters' design and their
Jacobian columns, and the columns of the parameters that enter only the motion's inputs,
carried by the chain rule through the slip, the spring and the Newton step.

Differenced through the whole evaluation instead, each column costs a motion, a torque
and an inverted step matrix per segment: most of a fit's time. Every function takes the
model it differentiates; ``Model`` keeps what they share at a point (``linearised``).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.diagnosis import balance, chain
from station.diagnosis.effects import friction
from station.diagnosis.hooks import Kept, TorqueParts
from station.diagnosis.layout import BlockKind
from station.diagnosis.motion import (
    COMMON_GAIN_SIGMA,
    TRIM_LAG_MAX,
    TRIM_LAG_SOFTEST,
    Inputs,
    Linearised,
    Motion,
    flatten,
)

if TYPE_CHECKING:
    from station.diagnosis.model import Model

ANGLE_STEP = 1e-6
"""Electrical rad: the step along the rotor angle that differences a smooth torque basis
into its slope (``linear_jacobian``)."""


def as_commanded(phase: int, base: NDArray[np.float64], d_i: NDArray[np.float64],
                 fine: NDArray[np.float64] | float) -> NDArray[np.float64]:
    """A change of a phase's current as the phase carries it, with no bridge that takes
    any of it back (``Hooks.current_kept``)."""
    return base


def linear_bases(model: Model, p: NDArray[np.float64], m: Motion) -> list[NDArray[np.float64]]:
    """∂(torque made)/∂β on the grid for each torque-side linear parameter β, in
    layout order: the currents' offsets and gains, then each effect's (its
    ``Hooks.bases``); friction's (which act on the needed torque) come separately."""
    pa, pb = model.magnet_weights(p, m)
    magnet = m.i_a * pa + m.i_b * pb
    sat = model.kt_factor(p, m.i_a, m.i_b)
    mod = m.modulation
    dsat_a, dsat_b = model.kt_slopes(p, m)
    d_ia = mod * (sat * pa + dsat_a * magnet)
    d_ib = mod * (sat * pb + dsat_b * magnet)
    for hook in model.each("beside_currents"):
        d_ia, d_ib = hook(model, p, m, d_ia, d_ib)
    _, ac_a, _, ac_b = model.current_coefficients(p)
    kept: Kept = as_commanded
    for hook in model.each("current_kept"):
        kept = hook(model, p, kept)
    parts = TorqueParts(magnet, sat, mod, model.inner_torque(p, m, magnet), d_ia, d_ib,
                        kept)
    gain = 1.0 + model.block(p, "amp_gain_error")
    changed = kept is not as_commanded  # what the finer grid is needed for

    def fine(ac: NDArray[np.complex128], phase: int) -> NDArray[np.float64] | float:
        return (ac @ model.fine_synth).real / gain[phase] if changed else 0.0

    bases = [kept(0, 1e-3 * d_ia, d_ia, 1e-3), kept(1, 1e-3 * d_ib, d_ib, 1e-3),
             kept(0, d_ia * (ac_a @ model.current_synth).real / gain[0], d_ia, fine(ac_a, 0)),
             kept(1, d_ib * (ac_b @ model.current_synth).real / gain[1], d_ib, fine(ac_b, 1))]
    # Friction's levels, filled in by ``linear_design``.
    bases += [np.zeros_like(m.te)] * model.layout.block("friction_coulomb").size
    for hook in model.each("bases"):
        bases += hook(model, p, m, parts)
    return bases


def design_and_bases(model: Model, p: NDArray[np.float64]) -> tuple[
        NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """``linear_design``, and the torque bases it was made from, (n, S, N)."""
    m = model.motion(p)
    bases = linear_bases(model, p, m)
    stacked = np.stack(bases) if bases else np.zeros((0, *m.te.shape))
    harmonic = model.analysed(stacked)
    dc = stacked.mean(axis=2)
    lay = model.layout
    shapes = model.friction_shapes_here(p)
    order = [b.name for b in lay.blocks if b.kind is BlockKind.LINEAR]
    row = sum(lay.block(n).size for n in order[:order.index("friction_coulomb")])
    for j in (0, 1):
        harmonic[row + j] = -m.transfer.d * model.analysed_cells(shapes[j])
        dc[row + j] = -model.gear_ratio * shapes[j].mean(axis=1)
    made, step = model.made_and_step(p)
    dc_scale = balance.dc_weight(model)
    beta = p[model.linear_index()]
    err = model.error(p, m, made) - np.tensordot(beta, harmonic, axes=1)
    err_dc = balance.dc_error(model, p, m, made) - beta @ dc
    # The prior is linear in the gain errors: its row is their mean over its σ.
    prior = np.zeros((len(beta), 1))
    gains = [i for i, n in enumerate(model.linear_names()) if n == "amp_gain_error"]
    prior[gains, 0] = 0.5 / COMMON_GAIN_SIGMA
    at_zero = flatten(step.apply(err), err_dc * dc_scale, np.zeros(1))
    design = np.array([flatten(h, d * dc_scale, q) for h, d, q in
                       zip(step.apply(harmonic), dc, prior, strict=True)]
                      ).reshape(len(beta), -1)
    return at_zero, design, stacked


def linear_jacobian(model: Model, p: NDArray[np.float64]) -> NDArray[np.float64]:
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
    _, design, bases = design_and_bases(model, p)
    lin = model.linearised(p)
    m, first = lin.motion, lin.first

    def slopes_of(here: NDArray[np.float64], at: Motion) -> NDArray[np.float64]:
        along = np.stack(linear_bases(model, p, at.shifted(ANGLE_STEP)))
        out: NDArray[np.float64] = (along - here) / ANGLE_STEP
        return out

    slopes = slopes_of(bases, m)
    bases1 = np.stack(linear_bases(model, p, first))
    slopes1 = slopes_of(bases1, first)
    d_lag = slip_change(model, lin, bases1.mean(axis=2), slopes1.mean(axis=2))
    # What the slip and the spring change: the torque made, and the step. The step's
    # own change, −step·(d matrix)·step(error), is the torque the changed spring makes
    # on the swing the step already asks for.
    d_slope = slopes + d_lag[:, :, None] * lin.bend[None]
    d_error = (d_lag[:, :, None] * model.analysed(lin.slope)[None]
               - model.rotor_teeth * model.analysed(d_slope * lin.swing[None]))
    d_dc = d_lag * lin.slope.mean(axis=1)
    dc_weight = balance.dc_weight(model)
    extra = np.array([flatten(h, d * dc_weight, np.zeros(1))
                      for h, d in zip(lin.step.apply(d_error), d_dc, strict=True)])
    out: NDArray[np.float64] = design + extra.reshape(design.shape)
    return out


def linearise(model: Model, p: NDArray[np.float64]) -> Linearised:
    m = model.motion(p)
    first = m.shifted(-m.lag)

    def slope_and_bend(at: Motion) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        slope = model.torque_slope(p, at)
        return slope, (model.torque_slope(p, at.shifted(ANGLE_STEP)) - slope) / ANGLE_STEP

    slope, bend = slope_and_bend(m)
    slope1, bend1 = slope_and_bend(first)
    spring1 = slope1.mean(axis=1)
    acts = ((np.abs(spring1) > TRIM_LAG_SOFTEST * model.amp[:, 0])
            & (np.abs(m.lag) < TRIM_LAG_MAX))
    made, step = model.made_and_step(p)
    alpha = step.alpha(model.error(p, m, made))
    swing = (model.rotor_response(m, alpha)[0] @ model.synth).real
    return Linearised(m, first, slope, bend, slope1, bend1, acts, step, alpha, swing)


def slip_change(model: Model, lin: Linearised, d_made1: NDArray[np.float64],
                 d_spring1: NDArray[np.float64],
                 d_load: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """How far each segment's slip (``trim_lag``: (level − made)/spring on the motion
    before it, where it acts) moves, (P, S), for changes of the torque made and of the
    spring there, and of an off-centre rotor's load (which moves the level), (P, S)
    each."""
    d_level = balance.condition_mean(model, d_made1)
    if d_load is not None:
        d_level = d_level + d_load - balance.condition_mean(model, d_load)
    safe = np.where(lin.acts, lin.spring1, np.inf)
    out: NDArray[np.float64] = (d_level - d_made1 - lin.motion.lag * d_spring1) / safe
    return out


def motion_columns(model: Model, p: NDArray[np.float64], points: list[NDArray[np.float64]],
                   steps: NDArray[np.float64]) -> NDArray[np.float64]:
    """d residuals / d parameter, (n, P), for parameters that enter only a motion's
    inputs (``Inputs``: the chain, the sensor, the friction, the load angles), each
    given as ``p`` moved by its ``steps`` entry (``points``).

    The inputs are differenced centrally (they are cheap) and carried through the rest
    by the chain rule: the rotor's swing moves its angle on the grid, and with it the torque
    made (the spring), the slip (``trim_lag``) and the spring itself, which changes
    the step (−step·(d matrix)·step(error), as in ``linear_jacobian``). Differenced
    through the whole evaluation instead, each column cost a motion, a torque and
    an inverted step matrix per segment: most of a fit's time. A point that moves
    the currents or the torque's own parameters is differenced whole.
    """
    lin = model.linearised(p)
    m = lin.motion
    here = model.inputs(p)
    index = model.torque_index
    opposite = [2.0 * p - x for x in points]
    chains = chain.chains(model, p, [*points, *opposite])
    inputs = [model.inputs(x, c) for x, c in zip(points, chains[:len(points)],
                                                 strict=True)]
    mirrored = [model.inputs(x, c) for x, c in zip(opposite, chains[len(points):],
                                                   strict=True)]
    whole = [i for i, (x, q) in enumerate(zip(inputs, points, strict=True))
             if not (np.array_equal(q[index], p[index]) and np.array_equal(x.i_a, here.i_a)
                     and np.array_equal(x.i_b, here.i_b)
                     and np.array_equal(x.modulation, here.modulation))]
    h = np.asarray(steps, dtype=np.float64)

    def d(pick: Callable[[Inputs], NDArray[Any]]) -> NDArray[Any]:
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
    d_ripple = (d_theta @ model.synth).real
    if here.swing_above is not None:
        above = here.swing_above

        def swing_above(x: Inputs) -> NDArray[np.complex128]:
            return above if x.swing_above is None else x.swing_above

        d_ripple = d_ripple + (d(swing_above) @ model.synth_beyond).real
    nr = model.rotor_teeth
    d_te1 = nr * d_ripple - d(lambda x: x.rho)[:, :, None]
    d_lag = slip_change(model, lin, (lin.slope1 * d_te1).mean(axis=2),
                              (lin.bend1 * d_te1).mean(axis=2),
                              d(lambda x: x.unbalance) if model.each("load") else None)
    d_te = d_te1 + d_lag[:, :, None]
    d_made = lin.slope * d_te
    # The chain's response and need to the step's acceleration (``rotor_response``).
    moved_theta, moved_need = d_a * lin.alpha, d_c * lin.alpha
    force = friction.friction_response(model, m.friction_slope, lin.alpha)
    d_force_step = friction.friction_response(model, d(lambda x: x.friction_slope), lin.alpha)
    moved_theta = moved_theta + d_b * force + t.b * d_force_step
    moved_need = moved_need + d_d * force + t.d * d_force_step
    d_need = d_c * m.alpha + t.c * d_alpha + d_d * m.friction + t.d * d_force
    moved_swing = (moved_theta @ model.synth).real
    d_step_torque = (nr * model.analysed(lin.bend * d_te * lin.swing
                                        + lin.slope * moved_swing)
                     - moved_need)
    d_error = model.analysed(d_made) - d_need
    factor = model.radius * model.weight
    harmonic = (d(lambda x: x.sensor) * factor * lin.alpha
                + lin.step.apply(d_error - d_step_torque))
    dc = ((d_made.mean(axis=2) - d(lambda x: x.taken)) * balance.dc_weight(model))
    prior = model.prior(p)
    out = np.stack([flatten(harmonic[i], dc[i],
                                  (model.prior(q) - prior) / steps[i])
                    for i, q in enumerate(points)], axis=1)
    if whole:
        base = model.residuals(p)
        for i in whole:
            out[:, i] = (model.residuals_near(points[i], p) - base) / steps[i]
    return out
