"""One ICD.md §5 metadata for tests that write or read logs by hand."""

from __future__ import annotations

from dataclasses import replace
from typing import Any

from station.core import Axis
from station.recording import RecordingMetadata

_DEFAULT = RecordingMetadata(
    serial="SN123",
    drive_node=1,
    sensor_node=16,
    sync_period_s=0.001,
    microsteps_per_fullstep=256,
    rotor_teeth=50,
    rated_current_mA=1000,
    sensor_lsb_mps2=2 * 9.80665 / 32768,  # the 2 g range
    tangential_axis=Axis.X,
    sensor_radius_m=0.1,
    gear_ratio=1.0,
)


def icd_metadata(**changes: Any) -> RecordingMetadata:
    """The ICD's example bench, with ``changes`` applied (any field, ``extra`` too)."""
    return replace(_DEFAULT, **changes)
