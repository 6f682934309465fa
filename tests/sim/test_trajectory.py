"""The drive's profile-velocity generator, as pure functions."""

from __future__ import annotations

import pytest

from station.sim import trajectory as traj

T = 1000  # µs
S = traj.VELOCITY_SCALE


def _run(target: int, cycles: int, ramp: traj.Ramp = traj.STANDSTILL,
         acc: int = 200_000, dec: int = 200_000) -> list[traj.Ramp]:  # fmt: skip
    out = []
    for _ in range(cycles):
        change = traj.velocity_change(ramp.velocity, target, acc, dec, T)
        ramp = traj.advance(ramp, change, T)
        out.append(ramp)
    return out


def test_velocity_ramps_at_the_profile_acceleration_and_lands_exactly_on_target() -> None:
    ramps = _run(target=1000, cycles=10, acc=200_000)
    velocities = [r.velocity / S for r in ramps]
    assert velocities[:5] == [200, 400, 600, 800, 1000]
    assert velocities[5:] == [1000] * 5


def test_slowing_down_uses_the_deceleration_not_the_acceleration() -> None:
    moving = traj.Ramp(0, 1000 * S)
    ramps = _run(target=0, cycles=3, ramp=moving, acc=200_000, dec=500_000)
    assert [r.velocity / S for r in ramps] == [500, 0, 0]


def test_reversal_stops_at_zero_then_accelerates_the_other_way() -> None:
    moving = traj.Ramp(0, 300 * S)
    ramps = _run(target=-1000, cycles=3, ramp=moving, acc=200_000, dec=200_000)
    # Crossing zero within a period is not allowed: the first period ends at rest.
    assert [r.velocity / S for r in ramps] == [100, 0, -200]


def test_position_demand_is_exact_for_velocities_without_a_binary_fraction() -> None:
    # 300 microsteps/s for 1 ms is 0.3 microsteps: float accumulation would drift off.
    ramp = traj.Ramp(0, 300 * S)
    positions = []
    for _ in range(1000):
        ramp = traj.advance(ramp, 0, T)
        positions.append(traj.position_demand(ramp))
    assert positions[9] == 3
    assert positions[99] == 30
    assert positions[-1] == 300


def test_position_demand_wraps_as_int32() -> None:
    just_below = traj.Ramp(((1 << 31) - 1) * traj.POSITION_SCALE, 0)
    assert traj.position_demand(just_below) == (1 << 31) - 1
    wrapped = traj.advance(just_below, 0, T)._replace(position=(1 << 31) * traj.POSITION_SCALE)
    assert traj.position_demand(wrapped) == -(1 << 31)
    assert traj.position_demand(traj.Ramp(-1, 0)) == -1  # floor, not truncation


def test_velocity_demand_truncates_toward_zero() -> None:
    assert traj.velocity_demand(traj.Ramp(0, 12_345_678)) == 12
    assert traj.velocity_demand(traj.Ramp(0, -12_345_678)) == -12


def test_kinematics_integrate_to_the_next_demand() -> None:
    ramp = traj.Ramp(7 * traj.POSITION_SCALE, 123 * S)
    change = traj.velocity_change(ramp.velocity, 5000, 33_333, 33_333, T)
    motion = traj.kinematics(ramp, change, T)
    t = T * 1e-6
    end = motion.position_start + motion.velocity * t + 0.5 * motion.acceleration * t * t
    assert end == pytest.approx(traj.advance(ramp, change, T).position / traj.POSITION_SCALE)
    assert motion.acceleration == pytest.approx(33_333)


def test_period_us_refuses_a_period_shorter_than_a_microsecond() -> None:
    assert traj.period_us(0.001) == 1000
    with pytest.raises(ValueError, match="1 µs"):
        traj.period_us(1e-7)
