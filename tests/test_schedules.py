"""Schedules hold whole electrical periods and follow the paper's sweeps."""

from __future__ import annotations

import pytest

from station.core import GAIN_UNITY
from station.schedules import (
    CharacterizationPlan,
    Phase,
    SweepPlan,
    calibration_schedule,
    characterization_schedule,
    cycles_for,
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
