"""Frames written at once (station.blf through RecordingWriter.write_frames) make the very
recording that frames given one by one make: same bytes, same losses."""

from __future__ import annotations

from dataclasses import fields
from pathlib import Path

import can
import numpy as np
import pytest
from numpy.typing import NDArray

from station.analysis import reader as reader_module
from station.blf import CanFrames, NotPlainCan, can_frame_chunks
from station.errors import RecordingError
from station.recorder import RecordingWriter
from tests.metadata import icd_metadata

Frames = tuple[NDArray[np.float64], NDArray[np.uint16], NDArray[np.uint8], NDArray[np.uint8]]


def _frames(count: int, seed: int = 5) -> Frames:
    """Frames of every length, with junk beyond each length that must not be written."""
    rng = np.random.default_rng(seed)
    stamps = 1.7e9 + 0.123456 + np.cumsum(rng.uniform(1e-5, 3e-4, count))
    cob_ids = rng.choice(np.array([0x080, 0x181, 0x190, 0x281, 0x7FF], dtype=np.uint16), count)
    lengths = rng.integers(0, 9, count).astype(np.uint8)
    payloads = rng.integers(0, 256, (count, 8)).astype(np.uint8)
    return stamps, cob_ids, lengths, payloads


def _one_by_one(path: Path, frames: Frames, loss: float) -> bytes:
    stamps, cob_ids, lengths, payloads = frames
    with RecordingWriter(path, icd_metadata(), loss_probability=loss, seed=11) as rec:
        for stamp, cob_id, length, payload in zip(stamps.tolist(), cob_ids.tolist(),
                                                  lengths.tolist(), payloads.tolist(),
                                                  strict=True):
            rec.on_message_received(can.Message(timestamp=stamp, arbitration_id=cob_id,
                                                is_extended_id=False, dlc=length,
                                                data=payload[:length]))
        rec.commit()
    return path.read_bytes()


def _at_once(path: Path, frames: Frames, loss: float) -> tuple[bytes, RecordingWriter]:
    with RecordingWriter(path, icd_metadata(), loss_probability=loss, seed=11) as rec:
        rec.write_frames(*frames)
        rec.commit()
    return path.read_bytes(), rec


@pytest.mark.parametrize(("count", "loss"), [(0, 0.0), (1, 0.0), (9_000, 0.0), (70_000, 0.03)])
def test_frames_at_once_are_the_bytes_python_can_writes_frame_by_frame(
        tmp_path: Path, count: int, loss: float) -> None:
    # 9,000 frames span four log containers, one object cut across each boundary; 70,000
    # need two blocks of loss draws.
    frames = _frames(count)
    expected = _one_by_one(tmp_path / "one.blf", frames, loss)
    written, rec = _at_once(tmp_path / "all.blf", frames, loss)
    assert written == expected
    assert rec.frames_seen == count
    assert rec.frames_written == len(list(can.LogReader(str(tmp_path / "all.blf"))))
    if loss:
        assert 0.02 < 1.0 - rec.frames_written / count < 0.04


def test_frames_at_once_into_another_format_are_its_frame_by_frame_recording(
        tmp_path: Path) -> None:
    frames = _frames(500)
    expected = _one_by_one(tmp_path / "one.csv", frames, 0.1)
    written, _ = _at_once(tmp_path / "all.csv", frames, 0.1)
    assert written == expected


def test_frames_at_once_are_refused_after_a_frame_by_frame(tmp_path: Path) -> None:
    stamps, cob_ids, lengths, payloads = _frames(3)
    with RecordingWriter(tmp_path / "r.blf", icd_metadata()) as rec:
        rec.on_message_received(can.Message(arbitration_id=0x80, is_extended_id=False,
                                            data=[1]))
        with pytest.raises(RecordingError, match="empty recording"):
            rec.write_frames(stamps, cob_ids, lengths, payloads)
    assert list(tmp_path.iterdir()) == []


def read_can_frames(path: Path) -> CanFrames | None:
    """Every frame of a plain log at once, None for any other."""
    try:
        chunks = list(can_frame_chunks(path))
    except NotPlainCan:
        return None
    return CanFrames(*(np.concatenate([getattr(c, f.name) for c in chunks])
                       for f in fields(CanFrames)))


def _python_can_log(path: Path, messages: list[can.Message], level: int = -1) -> None:
    writer = can.BLFWriter(str(path), compression_level=level)
    for message in messages:
        writer.on_message_received(message)
    writer.stop()


def _mixed(count: int) -> list[can.Message]:
    """Standard and extended ids, remote frames, received and sent, DLCs 0..8."""
    rng = np.random.default_rng(3)
    out = []
    for i in range(count):
        length = int(rng.integers(0, 9))
        out.append(can.Message(timestamp=1.7e9 + 0.37 + i * 1.7e-4, is_rx=bool(i % 3),
                               arbitration_id=int(rng.integers(0, 0x1FFFFFFF if i % 5 == 0
                                                               else 0x7FF)),
                               is_extended_id=i % 5 == 0, is_remote_frame=i % 7 == 0,
                               dlc=length, data=None if i % 7 == 0 else
                               bytes(rng.integers(0, 256, length).tolist())))
    return out


@pytest.mark.parametrize("level", [-1, 0])
def test_a_log_of_plain_frames_reads_as_arrays_exactly_as_python_can_reads_it(
        tmp_path: Path, level: int) -> None:
    path = tmp_path / "mixed.blf"
    _python_can_log(path, _mixed(6_000), level)
    frames = read_can_frames(path)
    assert frames is not None
    expected = list(can.BLFReader(str(path)))
    assert frames.timestamps.tolist() == [m.timestamp for m in expected]  # to the bit
    assert frames.arbitration_ids.tolist() == [m.arbitration_id for m in expected]
    assert frames.extended.tolist() == [m.is_extended_id for m in expected]
    assert frames.remote.tolist() == [m.is_remote_frame for m in expected]
    assert [bytes(row[:n]) for row, n in zip(frames.data, frames.lengths, strict=True)] == [
        bytes(m.data) for m in expected]


def test_a_log_holding_any_other_object_is_left_to_python_can(tmp_path: Path) -> None:
    errored = _mixed(50)
    errored.insert(20, can.Message(timestamp=errored[19].timestamp, is_error_frame=True))
    _python_can_log(tmp_path / "error.blf", errored)
    fd = _mixed(50)
    fd.insert(20, can.Message(timestamp=fd[19].timestamp, is_fd=True, data=bytes(12)))
    _python_can_log(tmp_path / "fd.blf", fd)
    late = _mixed(6_000)  # plain for two containers first: what was read is dropped
    late.append(can.Message(timestamp=late[-1].timestamp, is_error_frame=True))
    _python_can_log(tmp_path / "late.blf", late)
    _python_can_log(tmp_path / "whole.blf", _mixed(3_000))
    whole = (tmp_path / "whole.blf").read_bytes()
    (tmp_path / "cut.blf").write_bytes(whole[:len(whole) // 2])
    (tmp_path / "not.blf").write_bytes(b"date Tue Dec 1 2026\n" * 20)
    for name in ("error", "fd", "late", "cut", "not"):
        assert read_can_frames(tmp_path / f"{name}.blf") is None, name


def test_a_recording_read_as_arrays_is_the_recording_python_can_reads(tmp_path: Path) -> None:
    """The analysis reads a plain BLF log as arrays; what it keeps, ignores and counts
    malformed is what its frame-by-frame scan of python-can's messages gives."""
    path = tmp_path / "run.blf"
    messages = _mixed(2_000)
    for i in range(0, 2_000, 4):  # ICD frames among the others, some of a wrong length
        node = icd_metadata()
        cob_id = (0x080, 0x180 + node.drive_node, 0x280 + node.drive_node,
                  0x180 + node.sensor_node)[(i // 4) % 4]
        length = (1 if cob_id == 0x080 else 8) if i % 36 else 5
        messages[i] = can.Message(timestamp=messages[i].timestamp, arbitration_id=cob_id,
                                  is_extended_id=False, data=bytes(range(1, length + 1)))
    _python_can_log(path, messages)
    metadata = icd_metadata()
    frames = read_can_frames(path)
    assert frames is not None
    with can.BLFReader(str(path)) as reader:
        one_by_one = reader_module._scan(path, reader, metadata)
    at_once = reader_module._scan_chunks([frames], metadata)
    assert at_once.frames_malformed > 0 and at_once.frames_ignored > 0
    for field in ("frames_total", "frames_ignored", "frames_malformed"):
        assert getattr(at_once, field) == getattr(one_by_one, field), field
    np.testing.assert_array_equal(at_once.kinds, one_by_one.kinds)
    np.testing.assert_array_equal(at_once.payloads, one_by_one.payloads)
