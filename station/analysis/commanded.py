"""The drive's state as the station commanded it, for drives that do not report it.

A Modbus drive sends nothing on the CAN bus (ICD.md §4: no SYNC, no PDOs),
so a recording holds the sensor's samples but not the drive's position
demand, trims or statusword. The station knows what it wrote and between
which SYNCs each write was sent and acknowledged; this module turns that log
into the same per-sample drive columns a CANopen drive's TPDOs would have
given, so segmenting and demodulating stay one code path:

- the position demand is integrated from the commanded velocities, ramped at
  the drive's profile acceleration as the bench file states it. Its phase is
  arbitrary (the station never saw the drive's angle), so only magnitudes
  (the paper's method) may be taken from it;
- each write's effect is uncertain between its sending and its
  acknowledgement plus a guard time (the drive's own cycle, the network):
  those samples are marked not valid, so a hold never starts inside one.

Pure: lists and arrays in, a ``Timeline`` out.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any, Final

import numpy as np
from numpy.typing import NDArray

from station.analysis.timeline import Timeline
from station.errors import RecordingError

DRIVE_COMMANDS_KEY: Final = "drive_commands"
"""Recording metadata key (ICD.md §5 allows added keys) of the station's write log."""
DRIVE_STATE_KEY: Final = "drive_state"
"""Metadata key saying how the drive's state is known, and the guard time applied."""
STATION_SOURCE: Final = "station"

ENABLED_STATUSWORD: Final = 0x0027
"""CiA 402 operation enabled, as the synthesised statusword reads when enabled."""
DISABLED_STATUSWORD: Final = 0x0040
"""CiA 402 switch on disabled."""


@dataclass(frozen=True)
class Commanded:
    """The drive's whole set-point state after one write, and when it was written.

    ``sent`` and ``acknowledged`` count the SYNCs the station had seen when it
    sent the write and when the drive answered it: the write took effect at
    a sample in between (or at the drive's next cycle after).
    """

    sent: int
    acknowledged: int
    enabled: bool
    velocity: int  # microsteps/s
    amplitude_mA: int
    trims: tuple[int, int, int, int]  # offset A, offset B, gain A, gain B

    def to_json(self) -> dict[str, Any]:
        a, b, ga, gb = self.trims
        return {
            "sent": self.sent,
            "acknowledged": self.acknowledged,
            "enabled": self.enabled,
            "velocity": self.velocity,
            "amplitude_mA": self.amplitude_mA,
            "trims": {"offset_a_mA": a, "offset_b_mA": b, "gain_a": ga, "gain_b": gb},
        }

    @classmethod
    def from_json(cls, doc: Mapping[str, Any]) -> Commanded:
        trims = doc["trims"]
        return cls(
            sent=int(doc["sent"]),
            acknowledged=int(doc["acknowledged"]),
            enabled=bool(doc["enabled"]),
            velocity=int(doc["velocity"]),
            amplitude_mA=int(doc["amplitude_mA"]),
            trims=(int(trims["offset_a_mA"]), int(trims["offset_b_mA"]),
                   int(trims["gain_a"]), int(trims["gain_b"])),
        )


@dataclass(frozen=True)
class CommandTiming:
    """What the station assumes about a drive it cannot see: guard time and ramp."""

    guard_s: float  # after an acknowledgement, before a sample is trusted to show the write
    acceleration: float  # microsteps/s²: the drive's profile acceleration and deceleration

    def to_json(self) -> dict[str, Any]:
        return {"source": STATION_SOURCE, "guard_s": self.guard_s,
                "acceleration": self.acceleration}


def commands_from_metadata(extra: Mapping[str, Any]) -> tuple[list[Commanded], CommandTiming]:
    """The write log a Modbus run's recording carries, read strictly."""
    try:
        state = extra[DRIVE_STATE_KEY]
        timing = CommandTiming(float(state["guard_s"]), float(state["acceleration"]))
        commands = [Commanded.from_json(doc) for doc in extra[DRIVE_COMMANDS_KEY]]
    except (KeyError, TypeError, ValueError) as exc:
        raise RecordingError(f"metadata {DRIVE_COMMANDS_KEY!r}/{DRIVE_STATE_KEY!r} "
                             f"malformed: {exc!r}") from None
    if timing.guard_s < 0 or timing.acceleration <= 0:
        raise RecordingError(f"metadata {DRIVE_STATE_KEY!r}: guard_s must be ≥ 0 and "
                             "acceleration > 0")
    for c in commands:
        if c.acknowledged < c.sent:
            raise RecordingError(f"metadata {DRIVE_COMMANDS_KEY!r}: a write acknowledged "
                                 f"at sample {c.acknowledged} before it was sent ({c.sent})")
    return commands, timing


def velocity_profile(commands: Sequence[Commanded], samples: int,
                     step: float) -> NDArray[np.float64]:
    """Commanded velocity (microsteps/s) at samples 0..samples-1 of the log, ramped.

    Each target is approached from the acknowledgement on at ``step``
    microsteps/s per sample, as a profile-velocity drive does; a disabled
    drive's demand stops at once (it is de-energised).
    """
    v = np.zeros(samples)
    current = 0.0
    for i, c in enumerate(commands):
        start = min(max(0, c.acknowledged), samples)
        stop = samples if i + 1 == len(commands) else commands[i + 1].acknowledged
        stop = min(max(stop, start), samples)
        if not c.enabled:
            current = 0.0
            v[start:stop] = 0.0
            continue
        delta = float(c.velocity) - current
        n = np.arange(1, stop - start + 1, dtype=np.float64)
        v[start:stop] = current + np.sign(delta) * np.minimum(step * n, abs(delta))
        if stop > start:
            current = float(v[stop - 1])
    return v


def commanded_timeline(timeline: Timeline, commands: Sequence[Commanded],
                       timing: CommandTiming, *, first_sample: int = 0) -> Timeline:
    """``timeline`` with its drive columns rebuilt from the station's write log.

    ``first_sample`` is the log's count of the timeline's sample 0 (a live
    capture read from a bookmark starts later than the log). Samples before
    the first write, and from each write's sending to its acknowledgement
    plus the guard, are marked not valid.
    """
    n = timeline.samples
    period = timeline.sync_period_s
    ordered = sorted(commands, key=lambda c: (c.acknowledged, c.sent))
    amplitude = np.zeros(n, dtype=np.int32)
    statusword = np.full(n, DISABLED_STATUSWORD, dtype=np.uint16)
    trims = np.zeros((n, 4), dtype=np.int32)
    valid = np.zeros(n, dtype=bool)
    guard = int(np.ceil(timing.guard_s / period))
    for i, c in enumerate(ordered):
        start = max(0, c.acknowledged - first_sample)
        stop = n if i + 1 == len(ordered) else ordered[i + 1].acknowledged - first_sample
        stop = min(max(stop, 0), n)
        if stop > start:
            amplitude[start:stop] = c.amplitude_mA
            statusword[start:stop] = ENABLED_STATUSWORD if c.enabled else DISABLED_STATUSWORD
            trims[start:stop] = c.trims
            valid[start:stop] = True
    for c in ordered:
        lo = max(0, c.sent - first_sample)
        hi = min(n, c.acknowledged - first_sample + guard)
        if hi > lo:
            valid[lo:hi] = False
    # The profile runs in the log's samples from 0, so the ramp of a write made before
    # this timeline's start carries on into it.
    total = first_sample + n
    per_sample = velocity_profile(ordered, total, timing.acceleration * period) * period
    # Position at sample k: the travel over the periods before it (trapezoidal).
    travel = np.concatenate(([0.0], np.cumsum(0.5 * (per_sample[1:] + per_sample[:-1]))))
    position = travel[first_sample:]
    return replace(
        timeline,
        position=np.round(position).astype(np.int64),
        amplitude_mA=amplitude,
        statusword=statusword,
        drive_valid=valid,
        trims=trims,
        trims_valid=valid.copy(),
        drive_reported=False,
    )
