"""An effect is one module: written outside the package, it is fitted, named and reported.

This file is that module. It declares an effect the vocabulary does not have, cogging
written afresh as "tooth pull" (its own block, hooks, readout and rival), registers it,
and diagnoses a recording of a cogging unit with the vocabulary's own cogging withdrawn
from the search: the diagnosis has to lay out its parameters, compose its hooks into the
model's torque, its slope and its linear bases, search it beside rivals that can pose as
cogging (flux harmonics, current distortion), name it, and report its readout.
"""

from __future__ import annotations

from collections.abc import Iterator
from enum import StrEnum
from typing import TYPE_CHECKING, Any, cast

import numpy as np
import pytest
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis import effects, name
from station.diagnosis.diagnose import diagnose
from station.diagnosis.effects import EffectTerms, UnknownEffectError
from station.diagnosis.effects.readings import pair, sigmas
from station.diagnosis.hooks import Grid, Hooks, Params, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind
from station.diagnosis.report import render_html
from station.sim.concealed import PLANT_SUBSTEPS, Case, TrialClass, plan_trial
from station.sim.inprocess import simulate_timeline

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
    from station.diagnosis.observations import Observations
    from station.diagnosis.results import Diagnosis


class PluginEffect(StrEnum):
    """Ids beyond the vocabulary, as a plug-in would declare them."""

    TOOTH_PULL = "tooth_pull"


TOOTH_PULL = cast(Effect, PluginEffect.TOOTH_PULL)
"""The id as the diagnosis types its ids (any string enumeration serves)."""
ORDERS = (4, 8)


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    return [Block("tooth_pull", 2 * len(ORDERS), 0.0, -0.5, 0.5, BlockKind.LINEAR)]


def cogging(model: Model, p: Params, m: Motion, made: Grid) -> Grid:
    c = model.block(p, "tooth_pull")
    for i, order in enumerate(ORDERS):
        cos_n, sin_n = m.harmonic(order)
        made = made + c[2 * i] * sin_n + c[2 * i + 1] * cos_n
    return made


def cogging_slope(model: Model, p: Params, m: Motion, slope: Grid) -> Grid:
    c = model.block(p, "tooth_pull")
    for i, order in enumerate(ORDERS):
        cos_n, sin_n = m.harmonic(order)
        slope = slope + order * (c[2 * i] * cos_n - c[2 * i + 1] * sin_n)
    return slope


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    out: list[Grid] = []
    for order in ORDERS:
        cos_n, sin_n = m.harmonic(order)
        out += [parts.modulation * sin_n, parts.modulation * cos_n]
    return out


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sl = fit.model.layout.slices["tooth_pull"]
    values, errors = fit.params[sl], sigmas(cov)[sl]
    # Kt units (A) per ampere of the largest current: percent of the holding torque.
    scale = 100.0 / fit.model.largest_A
    return {f"order_{order}": pair(values[2 * i:2 * i + 2], errors[2 * i:2 * i + 2], scale)
            for i, order in enumerate(ORDERS)}


TERMS = EffectTerms(
    effect=TOOTH_PULL,
    blocks=blocks,
    readout=readout,
    healthy_part="Nothing kept: a test's effect.",
    rivals={Effect.FLUX_HARMONICS: "a test's rival: run at more currents"},
    grid_shared=True,
    hooks=Hooks(reads={Role.TORQUE: ("tooth_pull",)}, cogging=cogging,
                cogging_slope=cogging_slope, bases=bases),
)

SEARCHED = (TOOTH_PULL, Effect.FLUX_HARMONICS, Effect.CURRENT_DISTORTION)
"""What the search may name: the test's effect and two ids that can pose as cogging."""


@pytest.fixture
def registered() -> Iterator[None]:
    effects.register(TOOTH_PULL, __name__)
    yield
    effects.unregister(TOOTH_PULL)


@pytest.fixture(scope="module")
def cogging_unit() -> Any:
    """A development disk whose cogging the diagnosis names (seed 24: ``test_report``)."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.DETENT_TORQUE})), 24))
    return simulate_timeline(plan.unit, plan.schedule, seed=24, loss=plan.loss,
                             substeps=PLANT_SUBSTEPS)


def test_an_effect_declared_outside_the_package_is_fitted_named_and_reported(
        registered: None, cogging_unit: Any, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(name, "ids", lambda: SEARCHED)
    found: Diagnosis = diagnose(cogging_unit)
    named = {e.effect: e for e in found.effects}
    assert set(named) == {TOOTH_PULL}, found.to_dict()["effects"]
    doc = found.to_dict()
    entry = next(e for e in doc["effects"] if e["id"] == "tooth_pull")
    # Its readout, in its own units with σ, and a fit that improved where it is named.
    order_4 = entry["parameters"]["order_4"]
    assert order_4["magnitude"] > 5.0 * order_4["sigma"], entry
    assert named[TOOTH_PULL].held_out_gain_chi2 > 0.0
    assert "tooth_pull" in render_html(found, source="unit.blf")


def test_the_vocabulary_s_own_ids_cannot_be_replaced_by_a_registered_module() -> None:
    with pytest.raises(UnknownEffectError, match="vocabulary"):
        effects.register(Effect.DETENT_TORQUE, __name__)


def test_an_id_that_is_not_registered_is_refused_by_name(registered: None) -> None:
    effects.unregister(TOOTH_PULL)
    with pytest.raises(UnknownEffectError, match="tooth_pull"):
        effects.terms(TOOTH_PULL)
