"""What the operator sees the calibration doing: its steps, and whoever shows them."""

from __future__ import annotations

import logging
from enum import StrEnum
from typing import Protocol

log = logging.getLogger(__name__)


class Step(StrEnum):
    """What the operator sees the station doing."""

    CONNECT = "connect"
    IDENTIFY = "identify"
    SELF_CHECK = "sensor self-check"
    BASELINE = "baseline"
    SWEEP = "sweep"
    ESTIMATE = "estimate"
    WRITE = "write trims"
    STORE = "store"
    RESET = "reset"
    READ_BACK = "read back"
    VERIFY = "verify"
    RECORD = "calibration record"
    DONE = "done"


class Observer(Protocol):
    """Whoever shows the operator progress (the CLI's rich display, or nobody)."""

    def step(self, step: Step, detail: str) -> None: ...

    def progress(self, done: int, total: int) -> None: ...


class Silent:
    """An observer for callers that show nothing (tests, benchmarks)."""

    def step(self, step: Step, detail: str) -> None:
        log.info("%s: %s", step.value, detail)

    def progress(self, done: int, total: int) -> None:
        """Nothing to show."""
