"""Where the calibration measures: star designs, the paper's sweeps, hold lengths."""

from __future__ import annotations

from dataclasses import replace

import pytest

from station.core import GAIN_LIMITS, NOMINAL_TRIMS, Trims, offset_limit_mA
from station.designs import (
    gain_sweep,
    hold_cycles,
    holds_for,
    offset_a_sweep,
    offset_b_sweep,
    star,
    with_split,
    within_drive_range,
)
from station.schedules import Hold, Phase

RATED_mA = 1000  # the drive then accepts offsets within ±500 mA


def _split(t: Trims) -> float:
    return (t.gain_a - t.gain_b) / 2.0


# --- star -------------------------------------------------------------------------------------


def test_star_around_nominal_is_the_centre_and_plus_minus_step_on_each_axis() -> None:
    points = star(NOMINAL_TRIMS, 100, 1000, RATED_mA)
    assert points == [
        Trims(0.0, 0.0, 10000.0, 10000.0),
        Trims(100.0, 0.0, 10000.0, 10000.0),
        Trims(-100.0, 0.0, 10000.0, 10000.0),
        Trims(0.0, 100.0, 10000.0, 10000.0),
        Trims(0.0, -100.0, 10000.0, 10000.0),
        Trims(0.0, 0.0, 11000.0, 9000.0),
        Trims(0.0, 0.0, 9000.0, 11000.0),
    ]


def test_star_steps_around_an_off_nominal_centre_and_keeps_the_gain_sum() -> None:
    centre = Trims(40.0, -25.0, 10300.0, 9800.0)  # split +250, sum 20100
    points = star(centre, 30, 300, RATED_mA)
    assert len(points) == 7
    assert points[0] == centre
    offsets = {(p.offset_a_mA, p.offset_b_mA) for p in points}
    assert offsets == {(40.0, -25.0), (70.0, -25.0), (10.0, -25.0), (40.0, 5.0), (40.0, -55.0)}
    gain_points = points[5:]
    assert [_split(p) for p in gain_points] == [550.0, -50.0]
    for p in points:
        assert p.gain_a + p.gain_b == 20100.0
    # The gain points leave the offsets at the centre's.
    assert all((p.offset_a_mA, p.offset_b_mA) == (40.0, -25.0) for p in gain_points)


def test_star_rounds_every_point_to_whole_units_as_the_drive_stores_them() -> None:
    centre = Trims(12.4, -7.6, 10120.3, 9879.7)
    points = star(centre, 30, 300, RATED_mA)
    assert points[0] == Trims(12.0, -8.0, 10120.0, 9880.0)
    for p in points:
        assert p == p.rounded()
    assert Trims(42.0, -8.0, 10120.0, 9880.0) in points  # 12.4 + 30 = 42.4 -> 42


def test_star_clips_points_to_the_drive_range_and_drops_duplicates() -> None:
    limit = offset_limit_mA(RATED_mA)
    centre = Trims(float(limit), -480.0, 14500.0, 5500.0)  # at or near every edge
    points = star(centre, 100, 1000, RATED_mA)
    # +step on offset A lands back on the centre (clipped to +500): measured once.
    assert points == [
        Trims(500.0, -480.0, 14500.0, 5500.0),
        Trims(400.0, -480.0, 14500.0, 5500.0),
        Trims(500.0, -380.0, 14500.0, 5500.0),
        Trims(500.0, -500.0, 14500.0, 5500.0),
        Trims(500.0, -480.0, 15000.0, 5000.0),
        Trims(500.0, -480.0, 13500.0, 6500.0),
    ]
    low, high = GAIN_LIMITS
    for p in points:
        assert -limit <= p.offset_a_mA <= limit and -limit <= p.offset_b_mA <= limit
        assert low <= p.gain_a <= high and low <= p.gain_b <= high
    assert len(set(points)) == len(points)


def test_star_with_a_step_wider_than_the_range_collapses_both_sides_to_the_edges() -> None:
    points = star(NOMINAL_TRIMS, 2000, 8000, RATED_mA)
    assert Trims(500.0, 0.0) in points and Trims(-500.0, 0.0) in points
    assert replace(NOMINAL_TRIMS, gain_a=15000.0, gain_b=5000.0) in points
    assert replace(NOMINAL_TRIMS, gain_a=5000.0, gain_b=15000.0) in points
    assert len(points) == 7


# --- the paper's sweeps -----------------------------------------------------------------------


def test_offset_a_sweep_moves_offset_a_only_with_everything_else_nominal() -> None:
    points = offset_a_sweep(-500, 500, 11)
    assert [p.offset_a_mA for p in points] == [float(v) for v in range(-500, 501, 100)]
    assert all(replace(p, offset_a_mA=0.0) == NOMINAL_TRIMS for p in points)


def test_offset_b_sweep_holds_offset_a_at_its_estimate_rounded_to_whole_mA() -> None:
    points = offset_b_sweep(37.6, -200, 200, 5)
    assert [p.offset_b_mA for p in points] == [-200.0, -100.0, 0.0, 100.0, 200.0]
    assert {p.offset_a_mA for p in points} == {38.0}
    assert {(p.gain_a, p.gain_b) for p in points} == {(10000.0, 10000.0)}


def test_gain_sweep_keeps_the_gain_sum_at_20000_with_offsets_at_their_rounded_estimates() -> None:
    points = gain_sweep(-12.7, 40.2, 7000, 13000, 7)
    assert [p.gain_a for p in points] == [7000.0, 8000.0, 9000.0, 10000.0, 11000.0, 12000.0,
                                          13000.0]
    assert [p.gain_b for p in points] == [13000.0, 12000.0, 11000.0, 10000.0, 9000.0, 8000.0,
                                          7000.0]
    assert all(p.gain_a + p.gain_b == 20000.0 for p in points)
    assert {(p.offset_a_mA, p.offset_b_mA) for p in points} == {(-13.0, 40.0)}


def test_sweeps_space_points_evenly_in_whole_units() -> None:
    points = offset_a_sweep(-100, 100, 4)  # -100, -33.3, 33.3, 100
    assert [p.offset_a_mA for p in points] == [-100.0, -33.0, 33.0, 100.0]


# --- range and split --------------------------------------------------------------------------


def test_within_drive_range_clips_offsets_to_half_the_rated_current_and_gains() -> None:
    clipped = within_drive_range(Trims(730.2, -650.0, 16000.0, 4000.0), RATED_mA)
    assert clipped == Trims(500.0, -500.0, 15000.0, 5000.0)
    assert within_drive_range(Trims(730.2, -650.0), 2000) == Trims(730.0, -650.0)


def test_within_drive_range_rounds_values_already_in_range() -> None:
    assert within_drive_range(Trims(3.4, -3.6, 10000.4, 9999.6), RATED_mA) == Trims(
        3.0, -4.0, 10000.0, 10000.0
    )


def test_with_split_moves_the_gains_apart_symmetrically_keeping_their_sum() -> None:
    base = Trims(5.0, -5.0, 10200.0, 9900.0)  # centre 10050
    moved = with_split(base, 400.0)
    assert moved == Trims(5.0, -5.0, 10450.0, 9650.0)
    assert with_split(base, 0.0) == Trims(5.0, -5.0, 10050.0, 10050.0)
    assert with_split(base, -150.0).gain_a == 9900.0


# --- hold lengths -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("periods", "cycles"),
    [(1.0, 50), (12.0, 600), (0.5, 25), (0.01, 1), (0.0, 1), (1.01, 51)],
)
def test_hold_cycles_covers_whole_periods_at_20_hz_and_1_khz_rounding_up(
    periods: float, cycles: int
) -> None:
    assert hold_cycles(periods, 20.0, 0.001) == cycles


def test_hold_cycles_never_falls_short_of_the_periods_asked_for() -> None:
    # 30 Hz at 1 kHz: 33.3 samples per period; 3 periods are exactly 100.
    assert hold_cycles(1.0, 30.0, 0.001) == 34
    assert hold_cycles(3.0, 30.0, 0.001) == 100


def test_holds_for_gives_one_hold_per_point_and_the_first_is_longer_by_the_lead() -> None:
    points = [NOMINAL_TRIMS, Trims(100.0), Trims(-100.0)]
    holds = holds_for(
        points,
        phase=Phase.SWEEP_STAR,
        velocity=20480,
        amplitude_mA=1000,
        hold_periods=12,
        electrical_hz=20.0,
        sync_period_s=0.001,
        lead_periods=4,
    )
    assert holds == (
        Hold(Phase.SWEEP_STAR, 20480, 1000, NOMINAL_TRIMS, 800),
        Hold(Phase.SWEEP_STAR, 20480, 1000, Trims(100.0), 600),
        Hold(Phase.SWEEP_STAR, 20480, 1000, Trims(-100.0), 600),
    )


def test_holds_for_without_lead_gives_equal_holds() -> None:
    holds = holds_for(
        [NOMINAL_TRIMS, Trims(30.0)],
        phase=Phase.VERIFY,
        velocity=20480,
        amplitude_mA=800,
        hold_periods=20,
        electrical_hz=20.0,
        sync_period_s=0.001,
    )
    assert [h.cycles for h in holds] == [1000, 1000]
    assert {h.amplitude_mA for h in holds} == {800}
    assert holds_for([], phase=Phase.VERIFY, velocity=1, amplitude_mA=1, hold_periods=1,
                     electrical_hz=20.0, sync_period_s=0.001, lead_periods=4) == ()
