"""Whether a hold was still settling, judged from its two halves
(``segments.halves_shift``, ``pipeline.still_settling``): what lets the verification go on
measuring a unit that still rings, and only where that could change its verdict."""

from __future__ import annotations

import math

from station.analysis.pipeline import Measured, still_settling
from station.analysis.segments import Segment, halves_shift, steady_segments
from tests.analysis.test_segments import Run, _rung

RING = complex(-8.0, 2 * math.pi * 26.0)
"""A mode decaying in 0.125 s, rung by every change: over a hold of 6 periods after a
settle of 2 (0.1 s), its first half still carries three times what its second does."""


def _holds(amplitude: float) -> tuple[Run, list[Segment]]:
    run = _rung(8, RING, amplitude)
    segments, _ = steady_segments(run.timeline(), run.signal, settle_periods=2.0)
    return run, segments


def _measured(run: Run, seg: Segment) -> Measured:
    window = run.signal[seg.start:seg.stop]
    return Measured(seg, seg.harmonics(window, 2), 0, halves=seg.halves(window, 2))


def test_a_steady_hold_is_not_moving_at_either_order() -> None:
    run, segments = _holds(0.0)
    for seg in segments:
        halves = seg.halves(run.signal[seg.start:seg.stop], 2)
        assert halves is not None
        assert halves_shift(*halves, 1) == 0.0 and halves_shift(*halves, 2) == 0.0


def test_a_ringing_hold_is_moving_by_about_what_its_ring_left() -> None:
    run, segments = _holds(1.0)
    for seg in segments:
        halves = seg.halves(run.signal[seg.start:seg.stop], 2)
        assert halves is not None
        # At 0.1-0.25 s the ring is 0.14-0.45 m/s²: what moved lies between.
        assert 0.05 < halves_shift(*halves, 1) < 0.6


def test_a_ring_matters_only_near_a_limit() -> None:
    run, segments = _holds(1.0)
    m = _measured(run, segments[2])
    level = abs(m.harmonics.h(1))
    # A limit at the level measured could go either way; one far above cannot.
    assert still_settling(m, (level, 1e3)) == (1,)
    assert still_settling(m, (level + 10.0, 1e3)) == ()
    # Measured without halves, a hold is never taken for settling.
    bare = Measured(m.segment, m.harmonics, 0)
    assert still_settling(bare, (level, level)) == ()
