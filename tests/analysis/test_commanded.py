"""The drive's state rebuilt from the station's own writes (a Modbus drive sends no TPDOs)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis.commanded import (
    DRIVE_COMMANDS_KEY,
    DRIVE_STATE_KEY,
    Commanded,
    CommandTiming,
    commanded_timeline,
    commands_from_metadata,
    velocity_profile,
)
from station.analysis.estimate import TrimAxis, fit_parabola
from station.analysis.harmonics import period_phasors, phase_drift
from station.analysis.pipeline import (
    AnalysisOptions,
    estimate_condition,
    group_conditions,
    measure,
)
from station.analysis.segments import holds
from station.analysis.timeline import FrameKind, Timeline, build_timeline
from station.core import Method, MethodChoice
from station.errors import RecordingError
from tests.metadata import icd_metadata

PERIOD_S = 0.001
NOMINAL = (0, 0, 10000, 10000)


def _sensor_only_timeline(samples: int, accel: NDArray[np.int16] | None = None) -> Timeline:
    """A timeline of SYNCs and sensor frames only, as a Modbus run's bus carries."""
    kinds = np.empty(2 * samples, dtype=np.uint8)
    kinds[0::2], kinds[1::2] = FrameKind.SYNC, FrameKind.SENSOR
    payloads = np.zeros((2 * samples, 8), dtype=np.uint8)
    payloads[0::2, 0] = np.arange(samples) % 240 + 1
    counter = (np.arange(samples) % 65536).astype("<u2")
    payloads[1::2, 0:2] = counter.view(np.uint8).reshape(-1, 2)
    if accel is not None:
        xyz = np.zeros((samples, 3), dtype="<i2")
        xyz[:, 0] = accel
        xyz[:, 2] = 16384
        payloads[1::2, 2:8] = xyz.view(np.uint8).reshape(-1, 6)
    return build_timeline(icd_metadata(), kinds, payloads)


def _command(at: int, *, enabled: bool = True, velocity: int = 0,
             trims: tuple[int, int, int, int] = NOMINAL,
             latency: int = 0) -> Commanded:
    return Commanded(at, at + latency, enabled, velocity, 1000, trims)


def test_a_velocity_target_is_reached_at_the_profile_acceleration() -> None:
    commands = [_command(10, velocity=20480)]
    v = velocity_profile(commands, 400, 200_000 * PERIOD_S)
    assert v[9] == 0
    assert v[10] == pytest.approx(200)
    assert v[10 + 101] < 20480 == v[10 + 102]  # 20480 / 200 = 102.4 steps of 200
    assert np.all(np.diff(v) >= 0)


def test_samples_between_sending_and_acknowledgement_plus_guard_are_not_trusted() -> None:
    timing = CommandTiming(guard_s=0.005, acceleration=200_000)
    commands = [_command(0, velocity=10240), _command(500, trims=(10, 0, 10000, 10000),
                                                      velocity=10240, latency=3)]
    timeline = commanded_timeline(_sensor_only_timeline(1000), commands, timing)
    assert not timeline.drive_reported
    assert timeline.drive_valid[499] and not timeline.drive_valid[500]
    assert not timeline.drive_valid[507] and timeline.drive_valid[508]
    parts = [(h.start, h.trims) for h in holds(timeline)]
    # The new trims' hold starts only where the drive is trusted to hold them.
    assert parts[-1] == (508, (10, 0, 10000, 10000))


def test_a_bookmarked_stretch_carries_on_the_ramp_begun_before_it() -> None:
    timing = CommandTiming(guard_s=0.0, acceleration=100_000)
    commands = [_command(0, velocity=10240)]
    whole = commanded_timeline(_sensor_only_timeline(600), commands, timing)
    later = commanded_timeline(_sensor_only_timeline(300), commands, timing, first_sample=300)
    assert np.array_equal(np.diff(later.position), np.diff(whole.position[300:]))


def test_the_write_log_round_trips_through_recording_metadata() -> None:
    timing = CommandTiming(guard_s=0.02, acceleration=200_000)
    commands = [_command(5, velocity=-512, trims=(-3, 4, 9900, 10100), latency=2)]
    extra = {DRIVE_STATE_KEY: timing.to_json(),
             DRIVE_COMMANDS_KEY: [c.to_json() for c in commands]}
    assert commands_from_metadata(extra) == (commands, timing)


@pytest.mark.parametrize("broken", [
    {DRIVE_STATE_KEY: {"guard_s": 0.0}, DRIVE_COMMANDS_KEY: []},
    {DRIVE_STATE_KEY: {"guard_s": -1, "acceleration": 1}, DRIVE_COMMANDS_KEY: []},
    {DRIVE_STATE_KEY: {"guard_s": 0, "acceleration": 1},
     DRIVE_COMMANDS_KEY: [{"sent": 9, "acknowledged": 3, "enabled": True, "velocity": 0,
                           "amplitude_mA": 0, "trims": {"offset_a_mA": 0, "offset_b_mA": 0,
                                                        "gain_a": 0, "gain_b": 0}}]},
])
def test_a_malformed_write_log_is_a_recording_error(broken: dict[str, Any]) -> None:
    with pytest.raises(RecordingError):
        commands_from_metadata(broken)


@pytest.mark.parametrize("delta", [0.0, 0.002, -0.004])
def test_phase_drift_measures_how_far_the_true_frequency_is_from_the_assumed(delta: float) -> None:
    spp = 50.0
    n = np.arange(int(20 * spp))
    assumed = (2 * math.pi / spp) * n.astype(np.float64)
    truth = assumed * (1 + delta)
    signal = 0.3 * np.cos(truth + 0.4) + 0.1 * np.cos(2 * truth - 1.0)
    z = period_phasors(signal, np.ones(n.size, dtype=bool), assumed, spp, (1, 2))
    measured, sigma = phase_drift(z, (1, 2))
    assert sigma < 1e-5
    assert measured == pytest.approx(delta, abs=2e-5)


def test_a_drift_of_pure_noise_is_reported_as_indistinguishable_from_zero() -> None:
    spp = 50.0
    n = np.arange(int(20 * spp))
    assumed = (2 * math.pi / spp) * n.astype(np.float64)
    noise = np.random.default_rng(7).standard_normal(n.size)
    z = period_phasors(noise, np.ones(n.size, dtype=bool), assumed, spp, (1, 2))
    measured, sigma = phase_drift(z, (1, 2))
    assert abs(measured) < 3 * sigma


def test_a_lone_segment_at_the_null_keeps_the_commanded_speed() -> None:
    """The verification hold after trimming is mostly noise: its speed must not move."""
    velocity, samples = 20480, 2000
    commands = [_command(0, velocity=velocity)]
    noise = 0.003 * np.random.default_rng(11).standard_normal(samples)
    counts = np.round(noise / icd_metadata().sensor_lsb_mps2).astype(np.int16)
    timing = CommandTiming(guard_s=0.01, acceleration=200_000)
    timeline = commanded_timeline(_sensor_only_timeline(samples, counts), commands, timing)
    measured, _ = measure(timeline, AnalysisOptions(settle_periods=4))
    assert len(measured) == 1
    # The line fitted through whole microsteps, not a "correction" (noise gave 18.08 Hz).
    assert measured[0].segment.electrical_hz(PERIOD_S) == pytest.approx(20.0, rel=1e-6)


def test_magnitudes_survive_a_drive_clock_off_by_a_percent() -> None:
    """The paper's method on commanded angles: trims still come out at the parabola vertex."""
    samples_per_hold, velocity = 1000, 20480  # 20 Hz at 256 microsteps: 50 samples per period
    truth_hz = 20.0 * 1.01  # the drive's clock runs 1 % fast
    offsets = [-60, -30, 0, 30, 60]
    best_a = 12.0
    accel = np.zeros(samples_per_hold * (len(offsets) + 1))
    commands = [_command(0, velocity=velocity)]
    rng = np.random.default_rng(3)
    t = np.arange(accel.size) * PERIOD_S
    theta = 2 * math.pi * truth_hz * t
    for i, a in enumerate([0, *offsets]):
        start = i * samples_per_hold
        if i:
            commands.append(_command(start, velocity=velocity, trims=(a, 0, 10000, 10000)))
        h1 = 0.004 * (a - best_a)
        accel[start:start + samples_per_hold] = h1 * np.cos(theta[start:start + samples_per_hold])
    accel += 0.002 * rng.standard_normal(accel.size)
    counts = np.round(accel / icd_metadata().sensor_lsb_mps2).astype(np.int16)
    timing = CommandTiming(guard_s=0.01, acceleration=200_000)
    timeline = commanded_timeline(_sensor_only_timeline(accel.size, counts), commands, timing)
    measured, _ = measure(timeline, AnalysisOptions(settle_periods=2))
    assert len(measured) == len(offsets) + 1
    assert all(m.segment.electrical_hz(PERIOD_S) == pytest.approx(truth_hz, rel=1e-3)
               for m in measured)
    parabola, _ = fit_parabola([m.point() for m in measured], TrimAxis.OFFSET_A)
    assert parabola.vertex == pytest.approx(best_a, abs=1.0)
    condition = group_conditions(measured, PERIOD_S)[0]
    result = estimate_condition(condition, MethodChoice.AUTO, drive_reported=False)
    assert Method.COHERENT in result.unsupported
