"""Non-volatile memory of a simulated drive, one JSON file per unit.

A calibration is only worth something if the drive still holds it after a
power cycle, and ``station verify`` may run in another process days later; so
the simulated EEPROM lives in a file (``<state dir>/<serial>.json``), written
atomically so that a crash during "save" leaves the previous image intact, as
a real EEPROM with a double-buffered page would.
"""

from __future__ import annotations

import contextlib
import json
import os
import re
import tempfile
from collections.abc import Mapping
from pathlib import Path

from station.core import Trims
from station.errors import DeviceError

ObjectKey = tuple[int, int]
"""(index, subindex) of an object dictionary entry."""

FORMAT = "station-sim-eeprom/1"

_KEY = re.compile(r"0x([0-9A-F]{4}):([0-9A-F]{2})")


def key_text(key: ObjectKey) -> str:
    return f"0x{key[0]:04X}:{key[1]:02X}"


def _parse_key(text: str) -> ObjectKey:
    match = _KEY.fullmatch(text)
    if match is None:
        raise ValueError(f"object key {text!r} is not of the form 0xIIII:SS")
    return int(match.group(1), 16), int(match.group(2), 16)


TRIM_KEYS: tuple[ObjectKey, ...] = ((0x2100, 1), (0x2100, 2), (0x2100, 3), (0x2100, 4))
"""Object 0x2100, the four current trims (ICD.md §2)."""


def file_for(state_dir: Path, serial: str) -> Path:
    """Where unit ``serial`` (a label such as ``SN123``) keeps its image."""
    return state_dir / f"{serial}.json"


class Eeprom:
    """The stored image of one unit's persistent objects.

    ``factory`` is what an unprogrammed unit holds: it fixes which objects are
    persistent, and what "restore defaults" brings back.
    """

    def __init__(self, path: Path, serial: str, factory: Mapping[ObjectKey, int]) -> None:
        self.path = path
        self.serial = serial
        self._factory = dict(factory)
        stored = _read_image(path, serial) or {}
        foreign = sorted(stored.keys() - self._factory.keys())
        if foreign:
            raise DeviceError(
                "drive",
                f"EEPROM image {path} is unreadable: {key_text(foreign[0])} is not persistent",
            )
        self._stored = stored

    @classmethod
    def peek(cls, state_dir: Path, serial: str) -> Trims | None:
        """The trims unit ``serial`` has stored, without a device; None if it never stored."""
        stored = _read_image(file_for(state_dir, serial), serial)
        if stored is None or not all(key in stored for key in TRIM_KEYS):
            return None
        return Trims(*(float(stored[key]) for key in TRIM_KEYS))

    def image(self) -> dict[ObjectKey, int]:
        """What the unit loads at reset: stored values over the factory ones."""
        return {**self._factory, **self._stored}

    def store(self, values: Mapping[ObjectKey, int]) -> None:
        """Persist every persistent object at once (CiA 301 "save all parameters")."""
        missing = self._factory.keys() - values.keys()
        if missing:
            raise ValueError(f"store needs every persistent object, missing {sorted(missing)}")
        stored = {key: int(values[key]) for key in self._factory}
        document = {
            "format": FORMAT,
            "serial": self.serial,
            "objects": {key_text(key): value for key, value in sorted(stored.items())},
        }
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{self.path.name}.", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w", encoding="utf-8") as handle:
                json.dump(document, handle, indent=2)
                handle.write("\n")
                handle.flush()
                os.fsync(handle.fileno())
            os.replace(tmp, self.path)
        except BaseException:
            with contextlib.suppress(FileNotFoundError):
                os.unlink(tmp)
            raise
        self._stored = stored

    def erase(self) -> None:
        """Forget the stored image, so the next reset loads the factory values."""
        self.path.unlink(missing_ok=True)
        self._stored = {}


def _read_image(path: Path, serial: str) -> dict[ObjectKey, int] | None:
    try:
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        return None
    try:
        document = json.loads(text)
        if document.get("format") != FORMAT:
            raise ValueError(f"format is {document.get('format')!r}, expected {FORMAT!r}")
        if document.get("serial") != serial:
            raise ValueError(f"it belongs to {document.get('serial')!r}")
        stored: dict[ObjectKey, int] = {}
        for text_key, value in document["objects"].items():
            if not isinstance(value, int) or isinstance(value, bool):
                raise ValueError(f"{text_key} holds {value!r}, not an integer")
            stored[_parse_key(text_key)] = value
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        raise DeviceError("drive", f"EEPROM image {path} is unreadable: {exc}") from exc
    return stored
