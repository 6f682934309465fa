"""Recordings as ICD.md §5 defines them: a CAN log plus a metadata file.

What a recording is, and its metadata: read by the analysis and the diagnosis, so
nothing here needs a CAN library (``station.recorder`` writes the logs).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any, Final

from station.core import Axis
from station.errors import InputError, RecordingError

RECORDING_FORMAT: Final = "hsm-recording/1"

FRAMES_RECORDED_KEY: Final = "frames_recorded"
"""Metadata key this writer adds: every frame it wrote, so that a reader catches a
cut log even where the format has no end marker. Other benches may omit it."""



class LogFormat(StrEnum):
    """Log formats of ICD.md §5, by file suffix (all read by python-can's LogReader)."""

    ASC = ".asc"
    BLF = ".blf"
    CANDUMP = ".log"
    CSV = ".csv"
    MF4 = ".mf4"


def log_format_for(path: Path) -> LogFormat:
    """The format a recording path asks for; anything else is an input error."""
    try:
        return LogFormat(path.suffix.lower())
    except ValueError:
        known = ", ".join(f.value for f in LogFormat)
        raise InputError(
            f"{path}: unknown recording suffix {path.suffix!r}; use one of {known}"
        ) from None


def metadata_path_for(log_path: Path) -> Path:
    """ICD.md §5: the metadata file has the log's stem and the suffix ``.json``."""
    return log_path.with_suffix(".json")


def require_recording(log_path: Path) -> LogFormat:
    """The recording's format, refused when it names none or neither of its halves is
    there (that its metadata is missing would only confuse). Light on purpose: the
    command line asks it before the log readers are imported."""
    log_format = log_format_for(log_path)
    if not log_path.exists() and not metadata_path_for(log_path).exists():
        raise RecordingError(f"{log_path}: no such recording")
    return log_format


_REQUIRED_KEYS: Final[dict[str, type | tuple[type, ...]]] = {
    "format": str,
    "serial": str,
    "drive_node": int,
    "sensor_node": int,
    "sync_period_s": (int, float),
    "microsteps_per_fullstep": int,
    "rotor_teeth": int,
    "rated_current_mA": (int, float),
    "sensor_lsb_mps2": (int, float),
    "tangential_axis": str,
    "sensor_radius_m": (int, float),
    "gear_ratio": (int, float),
}


@dataclass(frozen=True)
class RecordingMetadata:
    """The keys ICD.md §5 requires, plus whatever else a writer adds (``extra``)."""

    serial: str
    drive_node: int
    sensor_node: int
    sync_period_s: float
    microsteps_per_fullstep: int
    rotor_teeth: int
    rated_current_mA: float
    sensor_lsb_mps2: float
    tangential_axis: Axis
    sensor_radius_m: float
    gear_ratio: float
    extra: Mapping[str, Any] = field(default_factory=dict)

    @property
    def sensor_full_scale_mps2(self) -> float:
        """The acceleration the sensor's range ends at: its sensitivity is range·g/32768
        (ICD.md §3, 0x2001), so the range is read back from the sensitivity alone."""
        return self.sensor_lsb_mps2 * 32768.0

    def to_json_dict(self) -> dict[str, Any]:
        doc: dict[str, Any] = {
            "format": RECORDING_FORMAT,
            "serial": self.serial,
            "drive_node": self.drive_node,
            "sensor_node": self.sensor_node,
            "sync_period_s": self.sync_period_s,
            "microsteps_per_fullstep": self.microsteps_per_fullstep,
            "rotor_teeth": self.rotor_teeth,
            "rated_current_mA": self.rated_current_mA,
            "sensor_lsb_mps2": self.sensor_lsb_mps2,
            "tangential_axis": self.tangential_axis.value,
            "sensor_radius_m": self.sensor_radius_m,
            "gear_ratio": self.gear_ratio,
        }
        for key, value in self.extra.items():
            doc.setdefault(key, value)
        return doc

    @classmethod
    def from_json_dict(
        cls, doc: Mapping[str, Any], *, source: str = "metadata"
    ) -> RecordingMetadata:
        """Strict reading: every ICD key present, of the right type and in range."""
        for key, kinds in _REQUIRED_KEYS.items():
            if key not in doc:
                raise RecordingError(f"{source}: missing key {key!r}")
            value = doc[key]
            if isinstance(value, bool) or not isinstance(value, kinds):
                raise RecordingError(f"{source}: key {key!r} has a malformed value {value!r}")
        if doc["format"] != RECORDING_FORMAT:
            raise RecordingError(
                f"{source}: key 'format' is {doc['format']!r}, expected {RECORDING_FORMAT!r}"
            )
        positive = (
            "sync_period_s",
            "microsteps_per_fullstep",
            "rotor_teeth",
            "rated_current_mA",
            "sensor_lsb_mps2",
            "sensor_radius_m",
            "gear_ratio",
        )
        for key in positive:
            if not math.isfinite(float(doc[key])) or float(doc[key]) <= 0:
                raise RecordingError(f"{source}: key {key!r} must be positive, got {doc[key]!r}")
        for key in ("drive_node", "sensor_node"):
            if not 1 <= int(doc[key]) <= 127:
                raise RecordingError(f"{source}: key {key!r} must be a node-ID 1..127")
        try:
            axis = Axis(str(doc["tangential_axis"]).lower())
        except ValueError:
            raise RecordingError(
                f"{source}: key 'tangential_axis' must be x, y or z, got {doc['tangential_axis']!r}"
            ) from None
        extra = {k: v for k, v in doc.items() if k not in _REQUIRED_KEYS}
        return cls(
            serial=str(doc["serial"]),
            drive_node=int(doc["drive_node"]),
            sensor_node=int(doc["sensor_node"]),
            sync_period_s=float(doc["sync_period_s"]),
            microsteps_per_fullstep=int(doc["microsteps_per_fullstep"]),
            rotor_teeth=int(doc["rotor_teeth"]),
            rated_current_mA=float(doc["rated_current_mA"]),
            sensor_lsb_mps2=float(doc["sensor_lsb_mps2"]),
            tangential_axis=axis,
            sensor_radius_m=float(doc["sensor_radius_m"]),
            gear_ratio=float(doc["gear_ratio"]),
            extra=extra,
        )


def read_metadata(log_path: Path) -> RecordingMetadata:
    """Load and validate the metadata beside a log."""
    path = metadata_path_for(log_path)
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise RecordingError(f"{log_path}: metadata file {path.name} is missing") from None
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read metadata: {exc.strerror}") from None
    except UnicodeDecodeError:
        raise RecordingError(f"{path}: metadata is not UTF-8 text") from None
    try:
        doc = json.loads(text)
    except json.JSONDecodeError as exc:
        raise RecordingError(
            f"{path}: metadata is not valid JSON ({exc.msg}, line {exc.lineno})"
        ) from None
    if not isinstance(doc, dict):
        raise RecordingError(f"{path}: metadata must be a JSON object")
    return RecordingMetadata.from_json_dict(doc, source=str(path))


def write_text_atomically(path: Path, text: str) -> None:
    """Write a text file so that readers see either the old file or the whole new one."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        tmp.write_text(text, encoding="utf-8")
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def write_json_atomically(path: Path, doc: Mapping[str, Any]) -> None:
    write_text_atomically(path, json.dumps(doc, indent=2, sort_keys=False) + "\n")


def sha256_of(path: Path) -> str:
    """The recording's fingerprint, kept with its run: a page drawn from it later can
    tell the file it reads from the one the unit was judged by."""
    digest = hashlib.sha256()
    with path.open("rb") as stream:
        for block in iter(lambda: stream.read(1 << 20), b""):
            digest.update(block)
    return digest.hexdigest()
