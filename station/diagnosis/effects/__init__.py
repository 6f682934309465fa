"""The vocabulary's effects as modules, one per id, found by id when first asked for.

Each module holds what the diagnosis knows of one id besides the torque it makes: the
parameters it adds (blocks), where a fit of them should start, how they read in physical
units with their σ, what a healthy unit always has of it (and whether the nominal model
keeps that), and its rivals with the experiment that tells them apart. So an effect is
read, changed or reviewed in one file, and a table of ids is never kept by hand.

A module is imported on first use, as python-can's backends are: reading a recording or
asking for one id's readout loads only what it needs. Its physics is a set of hook points
of the model (``station.diagnosis.hooks``), so the model composes what it is given and
never branches on an id; an effect outside the vocabulary (a plug-in, or a test's) is
added with ``register`` and is then searched, fitted, named and reported like the others.

The modules sit below the model and the fit (the layout, the hooks, the observations and
the core are all they import at run time); what they need of the fit is handed to them
(``Screen``), so the layers stay acyclic.
"""

from __future__ import annotations

import functools
import importlib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Final, TypeAlias

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.hooks import NO_HOOKS, Hooks
from station.errors import StationError

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import Block, ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.observations import Observations

Starts: TypeAlias = dict[str, list[float]]
"""Values for some named blocks, the others as the base has them."""
Params: TypeAlias = NDArray[np.float64]
Screen: TypeAlias = Callable[["Model", list[Params]], list[tuple[float, Params]]]
"""The fit's cheap ranking of starts (``fit.screen``), handed to an effect that ranks its
own: the effects sit below the fit."""

MODULES: Final[Mapping[Effect, str]] = {
    Effect.FLUX_HARMONICS: "flux_harmonics",
    Effect.CURRENT_DISTORTION: "current_distortion",
    Effect.DETENT_TORQUE: "detent_torque",
    Effect.RELUCTANCE_TORQUE: "reluctance_torque",
    Effect.LOAD_RESONANCE: "load_resonance",
    Effect.CURRENT_LOOP_LAG: "current_loop_lag",
    Effect.FRICTION: "friction",
    Effect.SENSOR_CLOCK_DRIFT: "sensor_clock_drift",
    Effect.MAGNETIC_SATURATION: "magnetic_saturation",
    Effect.ROTOR_ECCENTRICITY: "rotor_eccentricity",
}
"""Each id's module in this package."""

_REGISTERED: dict[Effect, str] = {}
"""Ids beyond the vocabulary's, each with its module's full dotted name (``register``)."""

DEFAULT_EXPERIMENT: Final = (
    "repeat the characterization with more speeds and currents, and trim steps of both signs, "
    "so that the two term groups' signatures (order, current scaling, load angle) part"
)
"""What separates two ids whose modules name no experiment for the pair."""


@dataclass(frozen=True)
class EffectTerms:
    """One id's declaration: its parameters, its physics as the model's hook points, and
    what the diagnosis says of it."""

    effect: Effect
    blocks: Callable[[ModelSpec, Observations], list[Block]]
    """The parameters the id adds, each starting where the effect is absent."""
    readout: Callable[[Fit, NDArray[np.float64]], dict[str, Any]]
    """The fitted parameters in physical units with their 1σ, from the fit and its
    covariance."""
    healthy_part: str
    """What a healthy unit always has of it, and what was decided: kept by the nominal
    model (fitted, reported, never named) or named whenever the data resolve it. Starts
    with "Kept" or "Nothing kept"."""
    nominal_blocks: Callable[[ModelSpec, Observations], list[Block]] | None = None
    """What a healthy unit always has of it, as parameters every model carries (fitted and
    reported by the nominal model, never named); the id's own ``blocks`` come on top."""
    rivals: Mapping[Effect, str] = field(default_factory=dict)
    """Ids the data can take it for, each with the experiment that separates the two (a pair
    is written down in one of its two modules)."""
    starts: Callable[[Model, Params], list[Starts]] | None = None
    """More than one start for its nonlinear parameters (None: the linear ones start at zero
    and are solved)."""
    estimates: Callable[[Model, Params, Screen], list[Starts]] | None = None
    """Starts the data estimate before any search: always searched from, whatever their χ²
    before the search."""
    far_starts: Callable[[Model, Params], list[Starts]] | None = None
    """Starts far from the base (another arrangement of its chain): ranked among themselves
    and polished apart."""
    tournament: bool = False
    """Every start goes to the short polish instead of the best two by their χ² before any
    polish (``fit.best_of``), with no first heat: its χ² before a polish says little about
    its basin."""
    grid_shared: bool = False
    """Tried alone on a bent nominal, its chain-grid first passes are made from one model
    holding every group that shares them (``fit.first_passes_shared``): every block of such
    a group starts at zero, where it leaves the nominal's motion as it is (the only
    nonlinear one, an eccentric rotor's unbalance, moves it only away from zero), so at a
    grid point it only adds rows to the linear design. The others (a coupling, a clock, a
    current loop's lag) start where the motion differs."""
    scan_trials: Callable[[Model], float] | None = None
    """How many independent models its starts were chosen among by a scan (the
    look-elsewhere effect; None: one)."""
    hooks: Hooks = NO_HOOKS
    """Where its physics acts on the model (the currents, the torque, the chain, the load,
    the sensor)."""


class UnknownEffectError(StationError):
    """An id the vocabulary has but no module declares: a packaging fault."""


def register(effect: Effect, module: str) -> None:
    """Add an id beyond the vocabulary, declared by ``module`` (a full dotted name whose
    ``TERMS`` is its ``EffectTerms``): a plug-in's, or a test's. Its module is imported
    on first use, as the vocabulary's are."""
    if effect in MODULES:
        raise UnknownEffectError(f"{effect!s} is the vocabulary's own and cannot be replaced")
    _REGISTERED[effect] = module
    terms.cache_clear()


def unregister(effect: Effect) -> None:
    """Take back an id ``register`` added (a test's, when it is done)."""
    _REGISTERED.pop(effect, None)
    terms.cache_clear()


def ids() -> tuple[Effect, ...]:
    """Every id the diagnosis knows: the vocabulary's, then the registered ones."""
    return (*Effect, *_REGISTERED)


@functools.cache
def terms(effect: Effect) -> EffectTerms:
    """The declaration of ``effect``, its module imported on first use."""
    if effect in MODULES:
        name = f"{__name__}.{MODULES[effect]}"
    elif effect in _REGISTERED:
        name = _REGISTERED[effect]
    else:
        raise UnknownEffectError(f"no module declares effect {effect!s}")
    declared = importlib.import_module(name).TERMS
    if not isinstance(declared, EffectTerms) or declared.effect is not effect:
        raise UnknownEffectError(f"module {name} does not declare {effect!s}")
    return declared


def every() -> tuple[EffectTerms, ...]:
    """Every id's declaration, in ``ids``'s order (imports them all)."""
    return tuple(terms(effect) for effect in ids())


def separating_experiment(a: Effect, b: Effect) -> str:
    """The experiment that tells ``a`` from ``b``, whichever of the two declares it."""
    return terms(a).rivals.get(b) or terms(b).rivals.get(a) or DEFAULT_EXPERIMENT


def nominal_blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    """Every id's healthy part that the nominal model carries, in the vocabulary's order."""
    return [block for t in every() if t.nominal_blocks is not None
            for block in t.nominal_blocks(spec, obs)]


def grid_shared() -> frozenset[Effect]:
    """The ids whose fits share the first passes over a bent nominal's chain grid."""
    return frozenset(t.effect for t in every() if t.grid_shared)


def scan_trials(model: Model) -> float:
    """How many independent models the groups of ``model`` were chosen among by a scan
    (1 when none was scanned)."""
    out = 1.0
    for effect in model.spec.effects:
        scanned = terms(effect).scan_trials
        if scanned is not None:
            out *= scanned(model)
    return out
