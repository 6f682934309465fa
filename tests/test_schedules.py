"""Schedules hold whole electrical periods and follow the paper's sweeps."""

from __future__ import annotations

import numpy as np
import pytest

from station.core import GAIN_UNITY, NOMINAL_TRIMS, Trims
from station.schedules import (
    RANDOM_CHARACTERIZATION,
    RANDOM_CHARACTERIZATION_NAME,
    CharacterizationPlan,
    Phase,
    Schedule,
    SweepPlan,
    calibration_schedule,
    characterization_schedule,
    cycles_for,
    random_characterization,
    velocity_for,
)


def test_velocity_is_four_full_steps_per_electrical_period() -> None:
    assert velocity_for(20.0, 256) == 20480


@pytest.mark.parametrize("hz", [7.0, 13.0, 20.0, 35.0])
def test_hold_lengths_cover_whole_electrical_periods(hz: float) -> None:
    cycles = cycles_for(0.5, hz, 0.001)
    periods = cycles * 0.001 * hz
    assert periods == pytest.approx(round(periods), abs=0.5 * 0.001 * hz + 1e-9)
    assert cycles * 0.001 >= 0.5 - 0.001


def test_calibration_sweeps_follow_the_paper() -> None:
    schedule = calibration_schedule(SweepPlan())
    a = [h.trims.offset_a_mA for h in schedule.holds if h.phase is Phase.SWEEP_OFFSET_A]
    b = [h.trims.offset_b_mA for h in schedule.holds if h.phase is Phase.SWEEP_OFFSET_B]
    gains = [
        (h.trims.gain_a, h.trims.gain_b) for h in schedule.holds if h.phase is Phase.SWEEP_GAIN
    ]
    assert a[0] == -500 and a[-1] == 500 and len(a) == 11
    assert b == a
    assert gains[0] == (7000.0, 13000.0) and gains[-1] == (13000.0, 7000.0)
    assert all(ga + gb == 2 * GAIN_UNITY for ga, gb in gains)
    assert schedule.holds[0].velocity == 0 and schedule.holds[-1].velocity == 0
    assert 30_000 < schedule.cycles < 40_000


def test_characterization_covers_both_directions_three_currents_and_trim_steps() -> None:
    schedule = characterization_schedule(CharacterizationPlan())
    moving = [h for h in schedule.holds if h.velocity != 0]
    assert {h.velocity > 0 for h in moving} == {True, False}
    assert len({abs(h.velocity) for h in moving}) >= 3
    assert len({h.amplitude_mA for h in moving}) >= 3
    assert {h.phase for h in moving} >= {Phase.STEP_OFFSET_A, Phase.STEP_OFFSET_B, Phase.STEP_GAIN}
    assert 35_000 < schedule.cycles < 55_000


def _draws(count: int = 200) -> list[Schedule]:
    return [random_characterization(np.random.default_rng(seed)) for seed in range(count)]


def test_random_characterizations_stay_within_their_ranges() -> None:
    r = RANDOM_CHARACTERIZATION
    rated = 1000
    for schedule in _draws():
        assert schedule.name == RANDOM_CHARACTERIZATION_NAME
        assert schedule.sensor_range_g in (4, 8, 16)
        moving = [h for h in schedule.holds if h.velocity != 0]
        speeds = {abs(h.velocity) for h in moving}
        assert 2 <= len(speeds) <= 6
        for v in speeds:
            assert 5.0 <= v / (4 * 256) <= 40.0
        # Every speed in both directions.
        assert {h.velocity for h in moving} == {s * d for s in speeds for d in (1, -1)}
        amplitudes = {h.amplitude_mA for h in moving}
        assert 2 <= len(amplitudes) <= 4
        assert all(r.lowest_amplitude_mA <= a <= rated for a in amplitudes)
        assert max(amplitudes) >= 0.8 * rated
        # One hold length for all, not rounded to periods: 0.4-1.0 s.
        lengths = {h.cycles for h in schedule.holds}
        assert len(lengths) == 1
        assert 400 <= lengths.pop() <= 1000
        assert schedule.holds[0].phase is Phase.STANDSTILL
        assert schedule.holds[-1].phase is Phase.STOP
        _check_trim_steps(schedule)


def _check_trim_steps(schedule: Schedule) -> None:
    """Each condition: a hold at the centre, then the offset and gain steps."""
    center = NOMINAL_TRIMS
    offsets: set[float] = set()
    gains: set[float] = set()
    conditions = 0
    for i, hold in enumerate(schedule.holds):
        if hold.phase is Phase.CONDITION:
            conditions += 1
            assert hold.trims == center
            after = schedule.holds[i + 1]
            assert after.phase is Phase.STEP_OFFSET_A
            assert (after.velocity, after.amplitude_mA) == (hold.velocity, hold.amplitude_mA)
        elif hold.phase in (Phase.STEP_OFFSET_A, Phase.STEP_OFFSET_B):
            offsets.add(hold.trims.offset_a_mA + hold.trims.offset_b_mA)
        elif hold.phase is Phase.STEP_GAIN:
            assert hold.trims.gain_a + hold.trims.gain_b == 2 * GAIN_UNITY
            gains.add(hold.trims.gain_a - GAIN_UNITY)
    speeds = {abs(h.velocity) for h in schedule.holds if h.velocity}
    amplitudes = {h.amplitude_mA for h in schedule.holds if h.velocity}
    assert conditions == 2 * len(speeds) * len(amplitudes)
    step = max(offsets)
    assert 20 <= step <= 80
    assert offsets in ({step}, {step, -step})
    gain = max(gains)
    assert 200 <= gain <= 800
    assert gains == ({gain} if len(offsets) == 1 else {gain, -gain})


def test_random_characterizations_vary_what_they_may() -> None:
    draws = _draws()
    assert {s.sensor_range_g for s in draws} == {4, 8, 16}
    assert {len({abs(h.velocity) for h in s.holds if h.velocity}) for s in draws} == {
        2, 3, 4, 5, 6}
    assert {len({h.amplitude_mA for h in s.holds if h.velocity}) for s in draws} == {2, 3, 4}
    both_signs = [any(h.trims.offset_a_mA < 0 for h in s.holds) for s in draws]
    assert any(both_signs) and not all(both_signs)
    first_direction = {next(h.velocity for h in s.holds if h.velocity) > 0 for s in draws}
    assert first_direction == {True, False}
    # Short holds at low speeds: fewer than ten periods, and not always whole ones.
    periods = [h.cycles * 0.001 * abs(h.velocity) / 1024 for s in draws for h in s.holds
               if h.velocity]
    assert min(periods) < 10
    assert any(abs(p - round(p)) > 0.1 for p in periods)


def test_random_characterization_is_the_seeds() -> None:
    first = random_characterization(np.random.default_rng(42), rated_current_mA=1200)
    again = random_characterization(np.random.default_rng(42), rated_current_mA=1200)
    other = random_characterization(np.random.default_rng(43), rated_current_mA=1200)
    assert first == again
    assert first != other


def test_random_characterization_steps_around_the_center_and_rating() -> None:
    center = Trims(12.0, -7.0, 10150.0, 9850.0)
    schedule = random_characterization(
        np.random.default_rng(7), microsteps=200, sync_period_s=0.002, rated_current_mA=700,
        center=center,
    )
    assert schedule.microsteps == 200
    assert all(h.amplitude_mA <= 700 for h in schedule.holds)
    assert {h.trims for h in schedule.holds if h.phase is Phase.CONDITION} == {center}
    assert all(200 <= h.cycles <= 500 for h in schedule.holds)
    for hold in schedule.holds:
        if hold.phase is Phase.STEP_GAIN:
            assert hold.trims.gain_a + hold.trims.gain_b == center.gain_a + center.gain_b
    with pytest.raises(ValueError, match="rated current"):
        random_characterization(np.random.default_rng(0), rated_current_mA=250)

