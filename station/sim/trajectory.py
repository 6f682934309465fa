"""The simulated drive's profile-velocity trajectory generator (CiA 402 pv mode).

Pure integer arithmetic on purpose: a real drive integrates its position
demand in fixed point, and so must the simulation, or the position reported
at SYNC n drifts by float rounding and a velocity of 300 microsteps/s would
show steps of 0 and 1 instead of a clean slope. Positions are kept in
``1/POSITION_SCALE`` microsteps and velocities in ``1/VELOCITY_SCALE``
microsteps/s; with the SYNC period in whole microseconds every quantity below
stays an exact integer.

Within one SYNC period the acceleration is constant (that is what the plant's
``DriveCommand`` can express). It is the profile acceleration or deceleration,
or less in the period that reaches the target, so the velocity lands exactly on
the target and never overshoots. A reversal stops at zero velocity at the end
of a period and accelerates the other way from the next one, so the
deceleration limit applies to slowing down and the acceleration limit to
speeding up, as CiA 402 prescribes.
"""

from __future__ import annotations

from typing import NamedTuple

VELOCITY_SCALE = 1_000_000
"""Velocity unit: 1e-6 microsteps/s (so velocity change = acceleration x period in µs)."""

POSITION_SCALE = 2 * VELOCITY_SCALE * VELOCITY_SCALE
"""Position unit: 1/(2e12) microsteps (so v·T + a·T²/2 is an integer with T in µs)."""

_INT32_SPAN = 1 << 32
_INT32_HALF = 1 << 31


class Ramp(NamedTuple):
    """Position and velocity demand at a SYNC instant, in the scaled units above."""

    position: int
    velocity: int


class Kinematics(NamedTuple):
    """One SYNC period's motion in plain units, for the plant."""

    position_start: float  # microsteps
    velocity: float  # microsteps/s at the start of the period
    acceleration: float  # microsteps/s², constant over the period


STANDSTILL = Ramp(0, 0)


def period_us(sync_period_s: float) -> int:
    """The SYNC period in whole microseconds (the unit CiA 301 uses in 0x1006)."""
    us = round(sync_period_s * 1e6)
    if us <= 0:
        raise ValueError(f"SYNC period must be at least 1 µs, got {sync_period_s} s")
    return us


def velocity_change(
    velocity: int, target: int, acceleration: int, deceleration: int, period: int
) -> int:
    """Velocity change (scaled) over one period towards ``target`` microsteps/s.

    ``acceleration`` and ``deceleration`` are the profile limits in
    microsteps/s² (0x6083, 0x6084); ``period`` is in µs.
    """
    wanted = target * VELOCITY_SCALE - velocity
    if wanted == 0:
        return 0
    slowing = velocity != 0 and (wanted > 0) != (velocity > 0)
    limit = (deceleration if slowing else acceleration) * period
    change = max(-limit, min(limit, wanted))
    if slowing and (velocity + change > 0) != (velocity > 0) and velocity + change != 0:
        # Crossing zero: stop at zero now, speed up with the acceleration limit next period.
        change = -velocity
    return change


def advance(ramp: Ramp, change: int, period: int) -> Ramp:
    """The demand at the end of a period starting at ``ramp``, changing velocity by ``change``."""
    # Δp = T·(v + Δv/2); in scaled units this is T_us·(2·v_u + Δv_u) exactly.
    return Ramp(ramp.position + period * (2 * ramp.velocity + change), ramp.velocity + change)


def kinematics(ramp: Ramp, change: int, period: int) -> Kinematics:
    return Kinematics(
        ramp.position / POSITION_SCALE,
        ramp.velocity / VELOCITY_SCALE,
        change / period,
    )


def position_demand(ramp: Ramp) -> int:
    """Object 0x6062: the position demand floored to microsteps, wrapping as an int32."""
    steps = ramp.position // POSITION_SCALE
    return (steps + _INT32_HALF) % _INT32_SPAN - _INT32_HALF


def velocity_demand(ramp: Ramp) -> int:
    """Object 0x606B: the velocity demand in whole microsteps/s, truncated toward zero."""
    whole = abs(ramp.velocity) // VELOCITY_SCALE
    return whole if ramp.velocity >= 0 else -whole
