"""The sensor's standstill self-check, on synthetic count arrays with a known LSB."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.typing import NDArray

from station.core import SATURATED_COUNTS, STANDARD_GRAVITY, Axis
from station.selfcheck import sensor_in_motion_problems, sensor_self_check

LSB = 2 * STANDARD_GRAVITY / 32768  # the 2 g range: 1 g is 16384 counts
G_COUNTS = 16384
TOLERANCE = 0.8  # m/s², as the shipped recipes
MAX_NOISE = 0.15  # m/s² rms
N = 300


def counts_at_rest(
    gravity: Axis = Axis.Z,
    *,
    sign: int = 1,
    noise_counts: float = 20.0,  # ≈ 0.012 m/s² rms
    n: int = N,
    seed: int = 0,
) -> NDArray[np.int16]:
    rng = np.random.default_rng(seed)
    raw = rng.normal(0.0, noise_counts, size=(n, 3))
    raw[:, gravity.column] += sign * G_COUNTS
    return np.asarray(np.round(raw), dtype=np.int16)


def check(counts: NDArray[np.int16], *, expected: int = N, gravity: Axis = Axis.Z) -> tuple[
    bool, tuple[str, ...]
]:
    result = sensor_self_check(
        counts,
        LSB,
        samples_expected=expected,
        gravity_axis=gravity,
        gravity_tolerance_mps2=TOLERANCE,
        max_noise_mps2=MAX_NOISE,
    )
    return result.ok, result.problems


def test_a_good_sensor_with_gravity_on_z_passes_and_reports_its_means_and_noise() -> None:
    counts = counts_at_rest(Axis.Z)
    result = sensor_self_check(
        counts, LSB, samples_expected=N, gravity_axis=Axis.Z,
        gravity_tolerance_mps2=TOLERANCE, max_noise_mps2=MAX_NOISE,
    )
    assert result.ok, result.problems
    assert result.problems == ()
    assert (result.samples_expected, result.samples_received) == (N, N)
    assert result.mean_mps2[2] == pytest.approx(STANDARD_GRAVITY, abs=0.01)
    assert result.mean_mps2[0] == pytest.approx(0.0, abs=0.01)
    assert result.mean_mps2[1] == pytest.approx(0.0, abs=0.01)
    for noise in result.noise_rms_mps2:
        assert noise == pytest.approx(20 * LSB, rel=0.15)
    doc = result.as_dict()
    assert doc["gravity_axis"] == "z" and doc["problems"] == []
    assert doc["samples_received"] == N


def test_gravity_on_the_wrong_axis_fails_naming_both_axes() -> None:
    ok, problems = check(counts_at_rest(Axis.X), gravity=Axis.Z)
    assert not ok
    text = "\n".join(problems)
    assert "axis z" in text and "expected gravity" in text
    assert "axis x" in text and "no static acceleration" in text
    assert "axis y" not in text


def test_a_sensor_mounted_upside_down_still_passes_on_the_magnitude() -> None:
    ok, problems = check(counts_at_rest(Axis.Y, sign=-1), gravity=Axis.Y)
    assert ok, problems


def test_gravity_just_outside_the_tolerance_fails_and_just_inside_passes() -> None:
    # Noise on every axis, or a constant axis would (rightly) be reported dead.
    inside = counts_at_rest(Axis.Z)
    outside = inside.copy()
    inside[:, 2] -= round(0.7 / LSB)
    outside[:, 2] -= round(0.9 / LSB)
    assert check(inside) == (True, ())
    ok, problems = check(outside)
    assert not ok
    assert len(problems) == 1 and problems[0].startswith("axis z reads +8.91")


def test_a_sensor_too_noisy_fails_naming_the_noise_of_each_noisy_axis() -> None:
    counts = counts_at_rest(Axis.Z, noise_counts=400.0)  # ≈ 0.24 m/s² rms
    ok, problems = check(counts)
    assert not ok
    noise_problems = [p for p in problems if "noise" in p]
    assert len(noise_problems) == 3
    assert all("rms exceeds 0.15 m/s²" in p for p in noise_problems)
    assert {p.split()[1] for p in noise_problems} == {"x", "y", "z"}


def test_too_few_samples_fails_saying_how_many_arrived() -> None:
    counts = counts_at_rest(n=200)
    ok, problems = check(counts, expected=300)  # 90 % of 300 is 270
    assert not ok
    assert problems == ("only 200 of 300 samples arrived at standstill",)


def test_ninety_percent_of_the_expected_samples_is_enough() -> None:
    assert check(counts_at_rest(n=270), expected=300)[0]


def test_fewer_than_ten_samples_fail_even_when_that_many_were_expected() -> None:
    ok, problems = check(counts_at_rest(n=5), expected=5)
    assert not ok
    assert problems[0] == "only 5 of 5 samples arrived at standstill"


@pytest.mark.parametrize("level", [SATURATED_COUNTS, -SATURATED_COUNTS, -32768])
def test_readings_at_full_scale_fail(level: int) -> None:
    counts = counts_at_rest()
    counts[10:13, 0] = level
    ok, problems = check(counts)
    assert not ok
    assert "3 readings at full scale while standing still" in problems


def test_zero_samples_give_a_result_with_problems_instead_of_a_crash() -> None:
    result = sensor_self_check(
        np.zeros((0, 3), dtype=np.int16), LSB, samples_expected=N, gravity_axis=Axis.Z,
        gravity_tolerance_mps2=TOLERANCE, max_noise_mps2=MAX_NOISE,
    )
    assert not result.ok
    assert result.samples_received == 0
    assert result.mean_mps2 == (0.0, 0.0, 0.0)
    assert result.problems == (f"only 0 of {N} samples arrived at standstill",)


def test_a_dead_axis_reading_exactly_zero_fails() -> None:
    counts = counts_at_rest(Axis.Z)
    counts[:, 0] = 0  # the tangential axis is dead
    ok, problems = check(counts)
    assert not ok
    assert len(problems) == 1
    assert problems[0].startswith("axis x never changes (+0.000 m/s² in every sample)")
    assert "dead or stuck" in problems[0]


@pytest.mark.parametrize("dead", list(Axis))
def test_a_dead_axis_is_named_whichever_it_is(dead: Axis) -> None:
    counts = counts_at_rest(Axis.Z)
    counts[:, dead.column] = 0
    ok, problems = check(counts)
    assert not ok
    assert [p.split()[1] for p in problems if "dead or stuck" in p] == [dead.value]


@pytest.mark.parametrize(
    ("stuck", "level"), [(Axis.X, 1), (Axis.Y, -35), (Axis.Z, G_COUNTS)]
)
def test_an_axis_stuck_at_a_plausible_non_zero_reading_fails(stuck: Axis, level: int) -> None:
    counts = counts_at_rest(Axis.Z)
    counts[:, stuck.column] = level
    ok, problems = check(counts)
    assert not ok
    assert [p.split()[1] for p in problems if "dead or stuck" in p] == [stuck.value]


def test_a_dead_axis_is_reported_once_not_also_as_noise() -> None:
    counts = counts_at_rest(Axis.Z, noise_counts=400.0)  # too noisy on y and z
    counts[:, 0] = 0  # and x dead
    ok, problems = check(counts)
    assert not ok
    assert [p.split()[1] for p in problems if "rms exceeds" in p] == ["y", "z"]
    assert [p.split()[1] for p in problems if "dead or stuck" in p] == ["x"]
    assert len(problems) == 3


def test_an_axis_that_moves_by_a_single_count_is_alive() -> None:
    counts = counts_at_rest(Axis.Z)
    counts[:, 1] = 0
    counts[N // 2, 1] = 1
    assert check(counts) == (True, ())


def test_too_few_samples_to_judge_do_not_also_call_an_axis_dead() -> None:
    counts = counts_at_rest(n=9)
    counts[:, 0] = 0
    ok, problems = check(counts, expected=9)
    assert not ok
    assert problems == ("only 9 of 9 samples arrived at standstill",)


# --- During the run: is a hold's data acceleration at all? -----------------------------


def in_motion(counts: NDArray[np.int16]) -> tuple[str, ...]:
    return sensor_in_motion_problems(counts, LSB, gravity_axis=Axis.Z,
                                     gravity_tolerance_mps2=TOLERANCE)


def vibrating(amplitude_counts: float, n: int = 2000) -> NDArray[np.int16]:
    """A running motor: a large tangential (X) ripple on top of the sensor at rest."""
    raw = counts_at_rest(n=n).astype(np.float64)
    raw[:, Axis.X.column] += amplitude_counts * np.sin(np.linspace(0, 40 * np.pi, n))
    return np.asarray(np.clip(np.round(raw), -SATURATED_COUNTS, SATURATED_COUNTS), dtype=np.int16)


def test_a_hold_that_clips_its_ripple_peaks_is_still_acceleration() -> None:
    counts = vibrating(60000.0)  # clips about half of the tangential samples
    clipped = np.mean(np.abs(counts[:, Axis.X.column]) >= SATURATED_COUNTS)
    assert 0.3 < clipped < 0.7
    assert in_motion(counts) == ()


def test_a_sensor_at_its_rails_is_refused_for_saturating() -> None:
    counts = np.where(vibrating(1000.0) >= 0, SATURATED_COUNTS, -SATURATED_COUNTS)
    problems = in_motion(np.asarray(counts, dtype=np.int16))
    assert any("saturates" in p for p in problems)


def test_an_unplugged_element_streaming_zeros_is_refused_for_missing_gravity() -> None:
    problems = in_motion(np.zeros((500, 3), dtype=np.int16))
    assert any("not gravity" in p for p in problems)
    assert any("never changes" in p for p in problems)


def test_an_element_that_dies_midway_through_a_hold_is_caught_by_gravity() -> None:
    counts = vibrating(2000.0)
    counts[len(counts) // 3:] = 0
    assert any("not gravity" in p for p in in_motion(counts))


def test_a_hold_without_any_sample_is_refused() -> None:
    assert in_motion(np.zeros((0, 3), dtype=np.int16)) == ("no sample arrived during the hold",)
