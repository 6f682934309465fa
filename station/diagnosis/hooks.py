"""Where an effect acts on the model: the hook points of its physics, one role each.

The model is one chain of physics: the drive makes currents from its table; the motor
makes torque from the currents and the rotor's angle; the chain of inertias and springs
carries it to the load, which other loads act on; the sensor reads the load's motion. An
effect of the vocabulary changes one or more links of that chain, and says which by the
hooks it fills in (``Hooks``). The model composes whatever hooks its effects have, in the
effects' order, and never asks which effect it holds: an effect is added by writing its
module (``station.diagnosis.effects``), not by editing the model.

Each hook is handed the model (for its observations, grid and parameter slices) and
returns its link as the model had it with its own part added: a transform, not a value,
so that the model's arithmetic is the same whether one effect acts on a link or none.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import TYPE_CHECKING, TypeAlias

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion

Params: TypeAlias = NDArray[np.float64]
Grid: TypeAlias = NDArray[np.float64]
"""Values on the model's grid, (S, N): one row per segment, one column per grid point."""
Phasors: TypeAlias = NDArray[np.complex128]


class Role(StrEnum):
    """The links of the model's chain an effect can act on; what a role's parameters
    change is kept and made again only when they move (``Model``'s memos)."""

    CURRENTS = "currents"  # the phase currents the drive makes
    TORQUE = "torque"  # the torque the motor makes of currents and angle
    CHAIN = "chain"  # the inertias, springs and dampers from rotor to load
    LOAD = "load"  # mean loads on the rotor beside the chain's own drag
    SENSOR = "sensor"  # what the sensor makes of the load's motion


@dataclass(frozen=True)
class Stage:
    """One inertia of the chain (μ = J/Kt, γ = c/Kt) and the spring to the next one."""

    inertia: float
    damping: float
    spring: float = 0.0  # κ = k/Kt of the spring to the next inertia (0: last inertia)
    spring_damping: float = 0.0
    ratio: float = 1.0  # next angle per this angle through the spring


Kept: TypeAlias = Callable[[int, Grid, Grid, "Grid | float"], Grid]
"""What a change of one phase's current becomes as the phase carries it (a bridge's
dead time takes some of it back): ``kept(phase, base, d_torque_d_i, fine)`` with ``base``
the torque basis of the change as commanded, ``d_torque_d_i`` the torque per ampere of the
phase, and ``fine`` the change on the current role's finer grid (``Model.fine_synth``)."""


@dataclass(frozen=True)
class TorqueParts:
    """The motor's torque at one point split as its linear bases need it
    (``jacobian.linear_bases``): τ = mod·(kt·magnet + cogging) + beside."""

    magnet: Grid  # i_A·∂τ/∂i_A + i_B·∂τ/∂i_B of the magnet alone
    kt: Grid | float  # the torque constant relative to its low-current value
    modulation: NDArray[np.float64]  # (S, 1)
    inner: Grid  # kt·magnet + cogging: what the modulation multiplies
    d_ia: Grid  # ∂τ/∂i_A, every term included
    d_ib: Grid
    kept: Kept


@dataclass(frozen=True)
class Hooks:
    """An effect's physics as hook points of the model, each None where it does not act.

    Composition: transforms are applied in the model's effect order, each on the link as
    the ones before left it; ``kt`` and ``modulation`` are factors (multiplied), ``load``
    a sum. ``reads`` says which of the effect's blocks each role reads: a role's kept
    pieces are made again when one of them moves, and go stale if one is missing.
    """

    reads: Mapping[Role, tuple[str, ...]] = field(default_factory=dict)

    # The currents: harmonics of each phase's waveform as (S, H) phasors, orders
    # ``Model.current_orders`` (1 and every effect's ``current_orders``).
    current_orders: tuple[int, ...] = ()
    """Harmonics of the commutation angle this effect adds to each phase's waveform."""
    current_wave: Callable[[Model, Params], tuple[Phasors, Phasors]] | None = None
    """Its harmonics of each phase's waveform per unit of the phase's amplitude, (H',)
    each, for its ``current_orders``."""
    current_response: Callable[[Model, Params, Phasors, Phasors],
                               tuple[Phasors, Phasors]] | None = None
    """Each phase's response at every current harmonic, (S, H) each, given the others'."""
    current_made: Callable[[Model, Params, Grid, Grid], tuple[Grid, Grid]] | None = None
    """The currents as the bridge makes them from the commanded ones, on the grid."""
    current_kept: Callable[[Model, Params, Kept], Kept] | None = None
    """``current_made``'s derivative, as what a change of a phase's current keeps."""

    # The torque: τ = mod·(kt·magnet + cogging) + beside.
    magnet: Callable[[Model, Params, Motion, Grid, Grid], tuple[Grid, Grid]] | None = None
    """∂(magnet torque)/∂i_A and ∂/∂i_B on the grid, given the others'."""
    magnet_slope: Callable[[Model, Params, Motion, Grid, Grid],
                           tuple[Grid, Grid]] | None = None
    """Those weights' derivative along the rotor's angle."""
    kt: Callable[[Model, Params, Grid, Grid], Grid] | None = None
    """A factor on the torque constant at the instantaneous currents."""
    kt_slope: Callable[[Model, Params, Motion], tuple[Grid, Grid]] | None = None
    """That factor's derivatives in i_A and i_B."""
    cogging: Callable[[Model, Params, Motion, Grid], Grid] | None = None
    """A torque of the rotor's angle alone, added to the magnet's."""
    cogging_slope: Callable[[Model, Params, Motion, Grid], Grid] | None = None
    modulation: Callable[[Model, Params], NDArray[np.float64]] | None = None
    """A factor on the magnet's and the cogging torque per segment, (S, 1)."""
    beside: Callable[[Model, Params, Motion, Grid], Grid] | None = None
    """A torque beside the magnet's (it does not pass through kt or the modulation)."""
    beside_slope: Callable[[Model, Params, Motion, Grid], Grid] | None = None
    beside_currents: Callable[[Model, Params, Motion, Grid, Grid],
                              tuple[Grid, Grid]] | None = None
    """∂τ/∂i_A and ∂/∂i_B with the beside torque's share added."""
    bases: Callable[[Model, Params, Motion, TorqueParts], list[Grid]] | None = None
    """∂τ/∂β on the grid for each of its linear parameters β, in its blocks' order."""

    # The chain, the load, the sensor.
    chain: Callable[[Model, Params, list[Stage]], list[Stage]] | None = None
    """The chain from rotor to load with its own stages put in."""
    load: Callable[[Model, Params], NDArray[np.float64]] | None = None
    """A mean load on the rotor per segment (Kt units, (S,))."""
    sensor: Callable[[Model, Params, NDArray[np.float64]], Phasors] | None = None
    """A factor on the sensor's response at orders ``k`` per segment, (S, K)."""


NO_HOOKS = Hooks()
"""An effect that changes no link of the model's chain (friction: the nominal model
carries the bearings' friction for every unit, and the id only frees its ceiling)."""
