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
"""How far the friction's harmonics are trusted where the load nearly stops (``Model.floor``):
to about a third, the spread between the common laws of friction at a reversal."""

FLOOR_SMOOTHING = 0.05
"""Of the slowest mean speed: the speed over which the friction of ``Model.turning_floor``
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
