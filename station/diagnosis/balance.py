"""The balance of mean torques: at constant speed what the motor makes on average meets
what the chain takes (its drag, the load's friction, an off-centre rotor's load), and each
segment's rotor slips along its magnetic spring until it does (``trim_lag``)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from station.diagnosis.motion import TRIM_LAG_MAX, TRIM_LAG_SOFTEST, Motion
from station.diagnosis.observations import MODEL_FLOOR

if TYPE_CHECKING:
    from station.diagnosis.model import Model


def condition_mean(model: Model, v: NDArray[np.float64]) -> NDArray[np.float64]:
    """The mean of ``v`` (…, S) over each segment's condition, at each segment."""
    cond = model.obs.condition
    conditions = len(model.obs.conditions)
    count = np.maximum(np.bincount(cond, minlength=conditions), 1)
    rows = np.atleast_2d(v)
    means = np.stack([np.bincount(cond, weights=r, minlength=conditions) / count
                      for r in rows])[:, cond]
    out: NDArray[np.float64] = means.reshape(np.shape(v))
    return out


def trim_lag(model: Model, p: NDArray[np.float64], m: Motion) -> NDArray[np.float64]:
    """How far each segment's rotor sits from its condition's load angle (electrical
    rad, (S,)): a trim step changes the mean torque the currents make on the swinging
    rotor (offsets and gain errors beating with the swing at orders 1 and 2), and the
    rotor slips along its magnetic spring until the mean torque again equals what the
    chain takes at that speed, the same for every segment of the condition but for an
    off-centre rotor's load (``unbalance``), which changes with each segment's
    mechanical angle.

    Near a mode that torque is several percent of the holding torque and moves with
    every step (a belt at 390 mA beside its 23 Hz mode: the condition's spread of it was
    21 times the balance's floor), so one angle per condition left the torque balance
    and the harmonics' phases wrong by as much. One Newton step along the spring from
    the condition's angle; the condition's mean torque, which its angle sets against
    the chain's drag, is kept.
    """
    made = model.torque(p, m).mean(axis=1)
    stiff = model.torque_slope(p, m).mean(axis=1)
    level = condition_mean(model, made)
    # The slope is −I·cos ρ (a restoring spring): the lag that brings each segment's
    # torque to its condition's level, capped where the spring is too soft to say.
    safe = np.where(np.abs(stiff) > TRIM_LAG_SOFTEST * model.amp[:, 0], stiff, np.inf)
    if model.each("load"):
        load = model.unbalance(p)
        level = level + load - condition_mean(model, load)
    shift = (level - made) / safe
    out: NDArray[np.float64] = np.clip(shift, -TRIM_LAG_MAX, TRIM_LAG_MAX)
    return out


def dc_weight(model: Model) -> NDArray[np.float64]:
    """1/σ of each segment's torque balance: the model floor of the holding torque
    (0 where the model leaves the balance out)."""
    out: NDArray[np.float64] = 1.0 / (MODEL_FLOOR * model.amp[:, 0])
    return out if model.spec.dc_balance else np.zeros_like(out)


def dc_error(model: Model, p: NDArray[np.float64], m: Motion,
             made: NDArray[np.float64] | None = None) -> NDArray[np.float64]:
    """Mean torque made minus mean torque taken (drag, and friction when modelled),
    per segment: at constant speed they must balance."""
    grid = model.torque(p, m) if made is None else made
    out: NDArray[np.float64] = grid.mean(axis=1) - m.taken
    return out
