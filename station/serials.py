"""Serial numbers: the label on the unit and the number in its EEPROM.

A label is ``SN`` followed by the decimal electronic serial number that the
drive reports in 0x1018:4 (U32). Labels also name files (EEPROM state of a
simulated unit, recordings), so anything else, path tricks included, is refused.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from station.errors import InputError

# [0-9], not \d: \d also matches other scripts' digits, which int() would quietly accept.
_LABEL = re.compile(r"SN(0|[1-9][0-9]{0,9})")
_U32_MAX = 0xFFFF_FFFF


@dataclass(frozen=True)
class Serial:
    label: str
    number: int

    def __str__(self) -> str:
        return self.label


def parse_serial(label: str) -> Serial:
    """Validate a serial label and return it with its electronic number."""
    match = _LABEL.fullmatch(label)
    if match is None:
        raise InputError(
            f"serial {label!r} is malformed: expected 'SN' followed by a decimal number"
            " without leading zeros, e.g. SN123"
        )
    number = int(match.group(1))
    if number > _U32_MAX:
        raise InputError(f"serial {label!r} does not fit the drive's 32-bit serial number")
    return Serial(label=f"SN{number}", number=number)


def label_for(number: int) -> str:
    """The label printed on a unit whose drive reports ``number`` in 0x1018:4."""
    return f"SN{number}"
