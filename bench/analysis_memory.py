"""Peak memory of analysing a 10-minute recording, measured in a child process.

A ten-minute log is 2.4 million frames: an analysis that held a Python object
per frame would need gigabytes. The recording is the shared 60 s one repeated
ten times end to end (``bench.tiling``), which takes seconds instead of the
minutes the lockstep bench needs to record it; the child is a fresh
interpreter, so its peak RSS is the whole cost of ``station analyze`` on it.
"""

from __future__ import annotations

import json
import resource
import sys
from pathlib import Path
from typing import Final

from bench.analysis_speed import MinuteRecording, analyse_log, run_child
from bench.record import BenchRecord, Goal
from bench.tiling import tile_recording
from station.recording import LogFormat

TARGET_MB: Final = 400.0
TILES: Final = 10
SEGMENTS_TOLERANCE: Final = 0.1
"""The tiled run must yield ten times the segments of one minute, give or take
this fraction; far off, it would not be the analysis of a ten-minute run."""

_PEAK_KEY: Final = "peak_kb"
_SEGMENTS_KEY: Final = "segments_used"
_STATUS: Final = Path("/proc/self/status")
_HIGH_WATER: Final = "VmHWM:"


def peak_rss_kb() -> int:
    """This process's own peak RSS.

    Not ``ru_maxrss``: Linux carries the parent's peak into a child started
    with vfork/exec (as ``subprocess`` does), so after the parent has tiled a
    long log the child would report the parent's high-water mark. ``VmHWM``
    belongs to the address space exec created. Elsewhere ru_maxrss is all
    there is.
    """
    if _STATUS.is_file():
        for line in _STATUS.read_text(encoding="ascii").splitlines():
            if line.startswith(_HIGH_WATER):
                return int(line.split()[1])
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss


def _child(log: Path) -> None:
    analysis = analyse_log(log)
    print(json.dumps({_PEAK_KEY: peak_rss_kb(), _SEGMENTS_KEY: analysis.segments_used}))


def _analyse_in_child(log: Path) -> tuple[float, int]:
    """Peak RSS in MB and segments used of one analysis in a fresh interpreter."""
    # The child reports its own peak: RUSAGE_CHILDREN would be the max over all children.
    report = json.loads(run_child(["bench.analysis_memory", str(log)]).splitlines()[-1])
    return float(report[_PEAK_KEY]) / 1024.0, int(report[_SEGMENTS_KEY])


def measure(minute: MinuteRecording) -> list[BenchRecord]:
    source = minute.path(LogFormat.BLF)
    folder = source.parent.parent / "tiled"
    folder.mkdir(exist_ok=True)
    tiled = tile_recording(source, folder / f"ten-minutes{LogFormat.BLF.value}", TILES).recording
    minute_peak, minute_segments = _analyse_in_child(source)
    peak, segments = _analyse_in_child(tiled)
    expected = TILES * minute_segments
    if abs(segments - expected) > SEGMENTS_TOLERANCE * expected:
        raise RuntimeError(
            f"the {TILES}-tile recording analysed into {segments} segments, "
            f"expected about {expected}: the tiling is not one continuous run"
        )
    return [
        BenchRecord("analysis_60s_peak_memory_blf", minute_peak, "MB", TARGET_MB, Goal.AT_MOST),
        BenchRecord("analysis_600s_peak_memory_blf", peak, "MB", TARGET_MB, Goal.AT_MOST),
    ]


if __name__ == "__main__":
    _child(Path(sys.argv[1]))
