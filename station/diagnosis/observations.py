"""What a diagnosis fits: every steady segment's harmonics 1..K, grouped by condition.

A condition is one operating point (current amplitude, signed speed). The
diagnosis compares models across conditions, so it keeps every segment, not
only those of the condition a calibration would use, and it keeps orders up
to 8: the effects it looks for live above the two orders the paper uses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from station.analysis.pipeline import AnalysisOptions, group_conditions, measure
from station.analysis.segments import Segment
from station.analysis.timeline import Timeline
from station.errors import InputError
from station.recording import RecordingMetadata

DIAGNOSIS_ORDERS = 8
"""Harmonic orders of the electrical frequency that a diagnosis models and maps."""

MIN_CONDITIONS = 3
"""Fewer conditions than this cannot hold one out and still fit the rest."""


class NotDiagnosable(InputError):
    """The recording does not hold the data a diagnosis needs; the message says which."""


@dataclass(frozen=True)
class ConditionKey:
    """One operating point as the drive reported it."""

    amplitude_mA: int
    electrical_hz: float  # signed: negative when the electrical angle decreases

    @property
    def direction(self) -> int:
        return 1 if self.electrical_hz > 0 else -1

    def label(self) -> str:
        return f"{self.amplitude_mA} mA, {self.electrical_hz:+.1f} Hz"

    def as_dict(self) -> dict[str, float | int | str]:
        return {
            "amplitude_mA": self.amplitude_mA,
            "electrical_hz": round(self.electrical_hz, 4),
            "direction": "forward" if self.direction > 0 else "reverse",
        }


@dataclass(frozen=True)
class Observations:
    """Per-segment arrays (S segments, K orders) and the conditions they belong to.

    ``phasors`` are the measured tangential acceleration harmonics in m/s²,
    referenced to the drive's reported electrical angle (ICD.md §2), as
    ``station.analysis.harmonics`` defines them; ``sigma`` their standard
    uncertainty (|Ĥ − H|, both parts together).
    """

    metadata: RecordingMetadata
    conditions: tuple[ConditionKey, ...]
    condition: NDArray[np.intp]  # (S,) index into ``conditions``
    amplitude_A: NDArray[np.float64]  # (S,) reported current amplitude
    omega: NDArray[np.float64]  # (S,) signed electrical angular speed, rad/s
    trims: NDArray[np.float64]  # (S, 4) offset A, offset B (mA), gain A, gain B (1/10000)
    phasors: NDArray[np.complex128]  # (S, K)
    sigma: NDArray[np.float64]  # (S, K)
    time_s: NDArray[np.float64]  # (S,) mid-segment instant from the first SYNC
    segments: tuple[Segment, ...]

    @property
    def orders(self) -> int:
        return int(self.phasors.shape[1])

    @property
    def count(self) -> int:
        return int(self.phasors.shape[0])

    def subset(self, keep: NDArray[np.bool_]) -> Observations:
        """The segments where ``keep`` is true, conditions renumbered."""
        used = sorted(set(self.condition[keep].tolist()))
        renumber = {old: new for new, old in enumerate(used)}
        return Observations(
            metadata=self.metadata,
            conditions=tuple(self.conditions[i] for i in used),
            condition=np.array([renumber[int(c)] for c in self.condition[keep]], dtype=np.intp),
            amplitude_A=self.amplitude_A[keep],
            omega=self.omega[keep],
            trims=self.trims[keep],
            phasors=self.phasors[keep],
            sigma=self.sigma[keep],
            time_s=self.time_s[keep],
            segments=tuple(s for s, k in zip(self.segments, keep, strict=True) if k),
        )


def observe(timeline: Timeline, *, orders: int = DIAGNOSIS_ORDERS) -> Observations:
    """Segment the run and demodulate every steady segment to ``orders`` harmonics.

    Segments where an order could not be fitted (too few samples per period
    for it) are dropped rather than carried with a NaN, so every row is whole.
    """
    measured, rejected = measure(timeline, AnalysisOptions(orders=orders))
    conditions = group_conditions(measured, timeline.sync_period_s)
    keys: list[ConditionKey] = []
    rows: list[tuple[int, object]] = []
    for condition in conditions:
        usable = [m for m in condition.measured if np.all(np.isfinite(m.harmonics.phasors))]
        if not usable:
            continue
        keys.append(ConditionKey(condition.amplitude_mA, condition.electrical_hz))
        rows.extend((len(keys) - 1, m) for m in usable)
    if len(keys) < MIN_CONDITIONS:
        why = "; ".join(sorted({r.reason for r in rejected})) or "no steady motion"
        raise NotDiagnosable(
            f"a diagnosis needs steady segments at {MIN_CONDITIONS} or more operating conditions "
            f"(speed, direction, current); this recording has {len(keys)} ({why})"
        )
    rows.sort(key=lambda row: row[1].segment.start)  # type: ignore[attr-defined]
    period = timeline.sync_period_s
    segs = [m.segment for _, m in rows]  # type: ignore[attr-defined]
    harmonics = [m.harmonics for _, m in rows]  # type: ignore[attr-defined]
    return Observations(
        metadata=timeline.metadata,
        conditions=tuple(keys),
        condition=np.array([c for c, _ in rows], dtype=np.intp),
        amplitude_A=np.array([s.amplitude_mA * 1e-3 for s in segs]),
        omega=np.array([2 * math.pi * s.electrical_hz(period) for s in segs]),
        trims=np.array(
            [[s.trims.offset_a_mA, s.trims.offset_b_mA, s.trims.gain_a, s.trims.gain_b]
             for s in segs]
        ),
        phasors=np.array([h.phasors for h in harmonics]),
        sigma=np.sqrt(np.array([h.variance for h in harmonics])),
        time_s=np.array([0.5 * (s.start + s.stop) * period for s in segs]),
        segments=tuple(segs),
    )
