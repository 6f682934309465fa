"""``bench.tiling``: a recording repeated end to end reads as one continuous run."""

from __future__ import annotations

import json
from pathlib import Path

import can
import numpy as np
import pytest

from bench.tiling import FrameRoles, shifted_payloads, tile_recording
from station.analysis.reader import read_recording
from station.analysis.timeline import Timeline
from station.core import NOMINAL_TRIMS, LoadKind, Trims
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

TILES = 3


def _short_schedule() -> Schedule:
    """750 samples: not a whole number of 240-count SYNC turns, so tiles must
    rewrite the SYNC counter; ends at standstill, as tiling requires."""
    v = velocity_for(20.0, 256)
    trims = Trims(offset_a_mA=-120.0, offset_b_mA=55.0, gain_a=9500.0, gain_b=10500.0)
    return Schedule(
        "short",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 100),
            Hold(Phase.BASELINE, v, 1000, NOMINAL_TRIMS, 250),
            Hold(Phase.SWEEP_OFFSET_A, v, 1000, trims, 250),
            Hold(Phase.STOP, 0, 1000, trims, 150),
        ),
    )


def _record(tmp_path: Path, loss: float) -> Path:
    out = tmp_path / "rec" / "short.blf"
    out.parent.mkdir()
    (tmp_path / "truth").mkdir()
    request = SimRecordRequest(
        out=out,
        serial=parse_serial("SN123"),
        schedule=ScheduleName.CALIBRATION,
        effects=frozenset(),
        seed=3,
        load=LoadKind.DISK,
        loss=loss,
        truth=tmp_path / "truth" / "short.truth.json",
    )
    record_schedule(request, _short_schedule())
    return out


def _tiled(array: np.ndarray, tiles: int = TILES) -> np.ndarray:
    return np.concatenate([array] * tiles)


@pytest.mark.parametrize("loss", [0.0, 0.02])
def test_tiled_recording_reads_as_one_run_with_counters_and_position_continuing(
    tmp_path: Path, loss: float
) -> None:
    source = _record(tmp_path, loss)
    result = tile_recording(source, tmp_path / "long.blf", TILES)
    one = read_recording(source)
    long = read_recording(result.recording)

    assert long.samples == TILES * one.samples
    # Every sensor frame lands on its own sample: no counter jumps at a seam.
    assert np.array_equal(long.sensor_valid, _tiled(one.sensor_valid))
    assert np.array_equal(long.accel_counts, _tiled(one.accel_counts))
    assert np.array_equal(long.drive_valid, _tiled(one.drive_valid))
    # The position demand goes on where the previous tile stopped.
    step = result.position_per_tile
    assert step > 0
    shifted = np.concatenate([one.position + k * step for k in range(TILES)])
    assert np.array_equal(long.position[long.drive_valid], shifted[long.drive_valid])
    neighbours = long.drive_valid[1:] & long.drive_valid[:-1]
    steps = np.diff(long.position)[neighbours]
    assert steps.min() >= 0 and steps.max() <= 21  # 20.48 microsteps per SYNC at most
    # Losses are the source's, once per tile, and none are invented at the seams.
    losses = one.losses
    assert long.losses.syncs_missing == TILES * losses.syncs_missing
    assert long.losses.sensor_samples_lost == TILES * losses.sensor_samples_lost
    assert long.losses.drive_status_lost == TILES * losses.drive_status_lost
    assert long.losses.frames_malformed == 0
    if loss == 0.0:
        assert long.losses.syncs_missing == 0 and long.losses.sensor_samples_lost == 0


def test_tiled_log_never_goes_back_in_time_and_its_metadata_counts_its_frames(
    tmp_path: Path,
) -> None:
    source = _record(tmp_path, 0.0)
    result = tile_recording(source, tmp_path / "long.blf", TILES)
    doc = json.loads((tmp_path / "long.json").read_text(encoding="utf-8"))
    with can.LogReader(str(result.recording)) as reader:
        stamps = np.array([msg.timestamp for msg in reader])
    # Set-up traffic before the first SYNC, repeated per tile, would go back.
    assert bool((np.diff(stamps) >= 0).all())
    assert doc["frames_recorded"] == result.frames_written == stamps.size
    assert doc["serial"] == "SN123"


def test_one_tile_in_another_format_reads_back_as_the_same_timeline(tmp_path: Path) -> None:
    source = _record(tmp_path, 0.02)
    copy = tile_recording(source, tmp_path / "copy.asc", 1).recording

    def rows(timeline: Timeline) -> tuple[np.ndarray, ...]:
        return (timeline.accel_counts, timeline.position, timeline.trims, timeline.statusword)

    one, other = read_recording(source), read_recording(copy)
    assert all(np.array_equal(a, b) for a, b in zip(rows(one), rows(other), strict=True))
    assert other.losses == one.losses


def test_shifted_counters_and_position_wrap_as_the_icd_types_do() -> None:
    data = np.zeros((3, 8), dtype=np.uint8)
    data[0, 0] = 240  # SYNC counter at the top of its 1..240 range
    data[1, 0:2] = np.array([65535], dtype="<u2").view(np.uint8)  # sensor counter, U16
    data[2, 0:4] = np.array([2**31 - 1], dtype="<i4").view(np.uint8)  # position, I32
    data[1, 2:8] = 7  # accelerations are not counters: left alone
    roles = FrameRoles(
        sync=np.array([True, False, False]),
        sensor=np.array([False, True, False]),
        drive_status=np.array([False, False, True]),
        first_sync=0,
    )
    out = shifted_payloads(data, roles, samples=1, position=1)
    assert out[0, 0] == 1
    assert out[1, 0:2].view("<u2")[0] == 0
    assert out[1, 2:8].tolist() == [7] * 6
    assert out[2, 0:4].view("<i4")[0] == -(2**31)
    assert data[0, 0] == 240  # the source rows are not modified


def test_fewer_than_one_tile_is_refused(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="at least 1"):
        tile_recording(tmp_path / "absent.blf", tmp_path / "out.blf", 0)
