"""The chain from rotor to load as the model has it: the stages the fixture declares (a
rigid disk, or a belt to a load) with what the effects put in (``Hooks.chain``), their
transfer at each order, many chains at once for a Jacobian, the drag they take and their
modes."""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from station.diagnosis.hooks import Stage
from station.diagnosis.layout import ChainKind
from station.diagnosis.motion import Chain, Motion, Stages, Transfer

if TYPE_CHECKING:
    from station.diagnosis.model import Model


def stages_at(model: Model, p: NDArray[np.float64]) -> list[Stage]:
    """The chain from rotor to load in units of Kt (see the module note)."""
    nr = model.rotor_teeth
    w1 = 2.0 * math.pi * math.exp(model.scalar(p, "log_rotor_hz"))
    inertia = nr / (w1 * w1)  # μ with rotor (and rigidly attached mass) on Nr·I at 1 A
    damping = 2.0 * model.scalar(p, "rotor_damping_ratio") * inertia * w1
    if model.spec.chain is ChainKind.RIGID:
        stages = [Stage(inertia, damping)]
    else:
        stages = _belt(model, p, inertia, damping)
    for hook in model.each("chain"):
        stages = hook(model, p, stages)
    return stages


def _belt(model: Model, p: NDArray[np.float64], inertia: float, damping: float) -> list[Stage]:
    """The rotor on the belt the fixture declares, and the load behind it."""
    n = model.gear_ratio
    mu_l = math.exp(model.scalar(p, "log_load_ratio")) * inertia / (n * n)
    wb = 2.0 * math.pi * math.exp(model.scalar(p, "log_belt_hz"))
    kb = mu_l * wb * wb
    cb = 2 * model.scalar(p, "belt_damping_ratio") * math.sqrt(kb * mu_l)
    load = Stage(mu_l, 2.0 * model.scalar(p, "load_damping_ratio") * mu_l * wb)
    return [Stage(inertia, damping, kb, cb, n), load]


def transfer(model: Model, stages: Sequence[Stage | Stages],
             s: NDArray[np.complex128] | None = None) -> Transfer:
    """Backwards from the load: each spring's twist carries the torque downstream of it
    (at the modelled orders unless ``s`` gives others); of many chains at once, (m, S,
    K) each, when ``stages`` holds them (``Stages``), every number the same as each
    chain's alone (the arithmetic is elementwise)."""
    s = model.jw if s is None else np.asarray(s, dtype=np.complex128)
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


def chain_at(model: Model, p: NDArray[np.float64]) -> Chain:
    """The chain at ``p`` (``Chain``)."""
    stages = stages_at(model, p)
    above = None if model.beyond is None else transfer(model, stages, model.jw_beyond).a
    return transfer(model, stages), above, drag(model, stages)


def chains(model: Model, p: NDArray[np.float64], points: list[NDArray[np.float64]]
           ) -> list[Chain | None]:
    """The chain at each of ``points`` whose chain parameters differ from ``p``'s, made
    in one batch (None for the others: theirs is ``p``'s).

    A Jacobian's chain columns each need a chain a step away, and one chain's transfer
    is a few dozen operations on arrays of a few hundred values, each paying numpy's
    call overhead: made one at a time, a belt's chains were an eighth of its
    diagnosis (development load_resonance@202, profiled), most of them a Jacobian's."""
    index = model.chain_index()
    key = p[index]
    moved = [i for i, x in enumerate(points) if not np.array_equal(x[index], key)]
    out: list[Chain | None] = [None] * len(points)
    if not moved:
        return out
    each = [stages_at(model, points[i]) for i in moved]
    batch = [Stages.of([stages[j] for stages in each]) for j in range(len(each[0]))]
    shape = (len(moved), *model.jw.shape)
    t = transfer(model, batch)
    a, b, c, d = (np.broadcast_to(x, shape) for x in (t.a, t.b, t.c, t.d))
    above = None
    if model.beyond is not None:
        above = np.broadcast_to(transfer(model, batch, model.jw_beyond).a,
                                (len(moved), *model.jw_beyond.shape))
    for n, (i, stages) in enumerate(zip(moved, each, strict=True)):
        out[i] = (Transfer(a[n], b[n], c[n], d[n]), None if above is None else above[n],
                  drag(model, stages))
    return out


def drag(model: Model, stages: list[Stage]) -> NDArray[np.float64]:
    """The mean torque the chain's own damping takes at each segment's speed, seen at
    the motor (Kt units): the viscous drag its ripple damping implies."""
    return drag_coefficient(stages) * model.obs.omega / model.rotor_teeth


def drag_coefficient(stages: list[Stage]) -> float:
    """The chain's viscous drag seen at the motor, Kt units per rad/s of the rotor:
    each stage's damping times its speed and its torque both geared back."""
    total, gear = 0.0, 1.0
    for st in stages:
        total += st.damping * gear * gear
        gear *= st.ratio
    return total


def modes(model: Model, p: NDArray[np.float64], amplitude_A: float,
          load_angle_rad: float = 0.0, spring: float | None = None
          ) -> list[tuple[float, float]]:
    """(frequency Hz, damping ratio) of the chain on its magnetic spring at a current,
    or on ``spring`` (Kt units per mechanical rad: ``swing_springs``) where given."""
    stages = stages_at(model, p)
    n = len(stages)
    mass = np.diag([st.inertia for st in stages])
    stiff = np.zeros((n, n))
    damp = np.diag([st.damping for st in stages])
    stiff[0, 0] = (model.rotor_teeth * amplitude_A * math.cos(load_angle_rad)
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


def rotor_hz(model: Model, p: NDArray[np.float64], amplitude_A: float,
             load_angle_rad: float = 0.0) -> float:
    """The rotor's own natural frequency on its magnetic spring at a current."""
    f1 = math.exp(model.scalar(p, "log_rotor_hz"))
    return f1 * math.sqrt(max(amplitude_A * math.cos(load_angle_rad), 1e-9))


def chain_response(model: Model, m: Motion) -> tuple[NDArray[np.complex128],
                                              NDArray[np.complex128]]:
    """Rotor angle and torque needed per unit of the load's acceleration, (S, K) each,
    friction linearised about its mean slope: the size of each order's balance
    (``magnification``). The step takes friction's whole derivative
    (``rotor_response``)."""
    t = m.transfer
    # A velocity moved alike at every point moves each step's friction by its band's sum.
    drag = m.friction_slope.sum(axis=1).mean(axis=1)[:, None] / model.jw
    return t.a + t.b * drag, t.c + t.d * drag
