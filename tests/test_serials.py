"""Serial labels name files and must match the drive's 32-bit serial number."""

from __future__ import annotations

import pytest

from station.errors import InputError
from station.serials import label_for, parse_serial


def test_label_carries_the_electronic_serial_number() -> None:
    serial = parse_serial("SN123")
    assert (serial.label, serial.number) == ("SN123", 123)
    assert label_for(serial.number) == "SN123"


@pytest.mark.parametrize(
    "label",
    ["", "123", "sn123", "SN", "SN0123", "SN12a", "../SN1", "SN1/../x", "SN1 ", "SN-1",
     "SN99999999999", "SN4294967296"],
)
def test_malformed_or_path_like_labels_are_refused(label: str) -> None:
    with pytest.raises(InputError, match="serial"):
        parse_serial(label)


def test_largest_u32_serial_is_accepted() -> None:
    assert parse_serial("SN4294967295").number == 0xFFFF_FFFF
