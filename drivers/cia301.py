"""CiA 301 vocabulary, shared by both ends of the bus.

The station's drivers and the simulated devices speak one protocol; naming its
constants once keeps the two ends from drifting apart. (The byte layouts of
ICD.md are checked independently, by hand-written formats in the tests.)
"""

from __future__ import annotations

from enum import IntEnum

NMT_COB_ID = 0x000
SYNC_COB_ID = 0x080
TPDO1_COB_BASE = 0x180
TPDO2_COB_BASE = 0x280
HEARTBEAT_COB_BASE = 0x700


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
