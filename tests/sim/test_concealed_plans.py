"""What a concealed trial's plan must hold before anything is diagnosed: a unit that could
run its schedule."""

from __future__ import annotations

import math

import pytest

from station.core import Effect
from station.sim.concealed import (
    FRICTION_HEADROOM,
    Case,
    TrialClass,
    plan_trial,
)


@pytest.mark.parametrize("seed", [26, 28])
def test_friction_with_its_viscous_part_stays_within_reach_of_every_moving_hold(
    seed: int,
) -> None:
    """Development belt units whose viscous drag at speed had taken the rotor to 83° of
    load angle, next to stalling, when only the Coulomb part was checked."""
    plan = plan_trial(Case(TrialClass(frozenset({Effect.FRICTION})), seed))
    unit, friction = plan.unit, plan.unit.mechanics.load_friction
    assert friction is not None
    worst = 0.0
    for hold in (h for h in plan.schedule.holds if h.velocity):
        electrical_hz = abs(hold.velocity) / (4.0 * plan.schedule.microsteps)
        load_rad_s = 2 * math.pi * electrical_hz / unit.motor.rotor_teeth * unit.gear_ratio
        needed = (max(friction.coulomb_pos_Nm, friction.coulomb_neg_Nm)
                  + friction.viscous_Nms * load_rad_s)
        capacity = unit.motor.holding_torque_Nm(hold.amplitude_mA / 1000) / unit.gear_ratio
        worst = max(worst, needed / capacity)
    assert worst <= FRICTION_HEADROOM + 1e-9

