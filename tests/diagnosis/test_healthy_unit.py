"""What a healthy unit has is nominal physics (CLI.md): the decisions, the ceiling, the
readings that rest on a limit."""

from __future__ import annotations

import math
from types import SimpleNamespace
from typing import Any

import pytest

from station.core import Effect
from station.diagnosis.effects import every
from station.diagnosis.effects.friction import (
    FRICTION_CEILING,
    HEALTHY_COULOMB,
    HEALTHY_COULOMB_GUARD,
    healthy_coulomb_ceiling,
)
from station.diagnosis.layout import ChainKind, ModelSpec
from station.diagnosis.model import layout_for
from station.diagnosis.results import sensor_bandwidth_hz


def _obs(rated_mA: int, gear_ratio: float) -> Any:
    """What the friction's ceiling reads of a recording: its metadata."""
    return SimpleNamespace(metadata=SimpleNamespace(rated_current_mA=rated_mA,
                                                    gear_ratio=gear_ratio))


def test_every_id_says_what_a_healthy_unit_has_of_it_and_what_was_decided() -> None:
    declared = every()
    assert [t.effect for t in declared] == list(Effect)
    assert all(t.healthy_part.startswith(("Kept", "Nothing kept")) for t in declared)


def test_the_healthy_ceiling_is_the_limit_with_its_guard_at_the_motor_shaft() -> None:
    disk = healthy_coulomb_ceiling(_obs(1000, 1.0))
    # Kt units at the load: the holding torque in Kt units is the rated current in A.
    assert disk == pytest.approx(HEALTHY_COULOMB * HEALTHY_COULOMB_GUARD * 1.0)
    assert HEALTHY_COULOMB == 0.10 and 1.0 < HEALTHY_COULOMB_GUARD < 1.5
    # Behind a 1:4 belt the same torque at the motor is four times as much at the load.
    assert healthy_coulomb_ceiling(_obs(2000, 0.25)) == pytest.approx(8.0 * disk)


def test_only_the_friction_group_frees_the_coulomb_levels_of_the_healthy_ceiling() -> None:
    obs = _obs(1000, 1.0)
    obs.conditions = [None] * 4
    obs.axis_mixed = False
    obs.metadata.sync_period_s = 1e-3
    nominal = layout_for(ModelSpec(ChainKind.RIGID), obs)
    named = layout_for(ModelSpec(ChainKind.RIGID, frozenset({Effect.FRICTION})), obs)
    other = layout_for(ModelSpec(ChainKind.RIGID, frozenset({Effect.DETENT_TORQUE})), obs)
    ceiling = healthy_coulomb_ceiling(obs)
    for layout, high in ((nominal, ceiling), (other, ceiling), (named, FRICTION_CEILING)):
        block = layout.block("friction_coulomb")
        assert (block.size, block.low, block.high) == (2, 0.0, high)
    # How sharply friction turns is the healthy unit's too: the group adds no block.
    assert nominal.has("log_friction_smoothing")
    assert [b.name for b in named.blocks] == [b.name for b in nominal.blocks]


def test_a_first_order_sensor_has_a_finite_bandwidth_where_its_curvature_is_zero() -> None:
    # 1/(1 + a1·s): −3 dB at 1/(2π·a1). The old reading, 1/(2π·√a2), was infinite here.
    assert sensor_bandwidth_hz(0.2, 0.0) == pytest.approx(1e3 / (2 * math.pi * 0.2))
    # Critically damped at ζ = 1/√2, the −3 dB point is the natural frequency.
    w0 = 2 * math.pi * 0.5  # rad/ms
    assert sensor_bandwidth_hz(math.sqrt(2) / w0, 1 / w0**2) == pytest.approx(500.0)
    assert sensor_bandwidth_hz(0.0, 0.0) is None
