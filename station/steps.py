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


    @property
    def number(self) -> int | None:
        """Which of the README's nine steps this is part of (None: outside them)."""
        return _NUMBER.get(self)


STEPS = 9
"""The calibration's steps as the README numbers them: the operator's "step n of 9"."""

_NUMBER = {
    Step.CONNECT: 1, Step.IDENTIFY: 1, Step.SELF_CHECK: 2, Step.BASELINE: 3, Step.SWEEP: 4,
    Step.ESTIMATE: 5, Step.WRITE: 6, Step.STORE: 6, Step.RESET: 6, Step.READ_BACK: 6,
    Step.VERIFY: 7, Step.RECORD: 9,
}


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
