"""CiA 301 vocabulary, shared by both ends of the bus and by what reads its recordings.

The station's drivers and the simulated devices speak one protocol; naming its
constants once keeps the two ends from drifting apart. It is part of the shared core
(with ``station.core`` and ``station.errors``), the only station modules the drivers
import, so that the analysis can read a recording's frames without importing a driver.
(The byte layouts of ICD.md are checked independently, by hand-written formats in the
tests.)
"""

from __future__ import annotations

from enum import IntEnum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
TPDO1_COB_BASE = 0x180
TPDO2_COB_BASE = 0x280
HEARTBEAT_COB_BASE = 0x700
SYNC_COUNTER_OVERFLOW = 240
"""The SYNC counter runs 1..240 (CiA 301 0x1019) and wraps: the station's SYNC producer
counts so, and recordings are read so."""


class NmtCommand(IntEnum):
    """NMT command specifiers (first byte of COB-ID 0x000)."""

    START_REMOTE_NODE = 0x01
    STOP_REMOTE_NODE = 0x02
    ENTER_PRE_OPERATIONAL = 0x80
    RESET_NODE = 0x81
    RESET_COMMUNICATION = 0x82


class NmtState(IntEnum):
    """NMT states as a heartbeat reports them (toggle bit masked off); 0 is boot-up."""

    BOOT_UP = 0x00
    STOPPED = 0x04
    OPERATIONAL = 0x05
    PRE_OPERATIONAL = 0x7F


class Signature(IntEnum):
    """Signatures written to 0x1010 (store, "save") and 0x1011 (restore, "load")."""

    SAVE = 0x65766173
    LOAD = 0x64616F6C


class AbortCode(IntEnum):
    """SDO abort codes the bench's devices give on purpose."""

    READ_ONLY = 0x06010002
    VALUE_RANGE = 0x06090030
    CANNOT_STORE = 0x08000020
    DEVICE_STATE = 0x08000022


ABORT_MEANINGS = {
    0x05040000: "SDO protocol timed out",
    0x06010000: "unsupported access to an object",
    0x06010001: "attempt to read a write-only object",
    AbortCode.READ_ONLY: "attempt to write a read-only object",
    0x06020000: "object does not exist in the object dictionary",
    0x06070010: "data type does not match",
    AbortCode.VALUE_RANGE: "value range of parameter exceeded",
    0x06090011: "sub-index does not exist",
    0x08000000: "general error",
    AbortCode.CANNOT_STORE: "data cannot be transferred or stored",
    0x08000021: "data cannot be stored because of local control",
    AbortCode.DEVICE_STATE: "data cannot be transferred in the present device state",
}
"""CiA 301's names for the abort codes a technician is likely to meet."""
