"""Stopping the station on SIGINT or SIGTERM without cutting its cleanup short.

A calibration that is stopped must still disable the drive, close the bus and
record the run as ``aborted``; only then may the process end. Python's default
SIGINT handling raises ``KeyboardInterrupt`` at every Ctrl-C, so an impatient
second Ctrl-C lands in the middle of that cleanup (drive left energised, run
left open), and SIGTERM (systemd, a line controller, ``kill``) ends the process
at once without any cleanup at all.

``stop_on_signals()`` makes both signals raise ``Stopped`` (a
``KeyboardInterrupt``, so every ``except KeyboardInterrupt`` in the station
treats it as the operator's stop) in the main thread, the first time only.
From then on the station is stopping: further signals are logged and ignored
until the block ends and the previous handlers are back. ``held()`` marks a
short critical section (a database write transaction): a first signal that
arrives inside it is delivered as ``Stopped`` as soon as the section ends, so
a commit is never cut in half.
"""

from __future__ import annotations

import logging
import signal
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from types import FrameType

log = logging.getLogger(__name__)

STOP_SIGNALS: tuple[signal.Signals, ...] = (signal.SIGINT, signal.SIGTERM)
"""What a line controller or an operator sends to stop the station."""

_REASONS = {
    signal.SIGINT: "aborted by the operator (SIGINT)",
    signal.SIGTERM: "stopped by SIGTERM",
}


def stop_reason(signum: int) -> str:
    """The reason a run stopped by ``signum`` is recorded with."""
    try:
        sig = signal.Signals(signum)
    except ValueError:
        return f"stopped by signal {signum}"
    return _REASONS.get(sig, f"stopped by {sig.name}")


class Stopped(KeyboardInterrupt):
    """The station was told to stop by a signal; ``str()`` is the reason to record.

    A ``KeyboardInterrupt`` so that code which already handles Ctrl-C (the
    service records the run as ``aborted``) handles SIGTERM the same way.
    """

    def __init__(self, signum: int) -> None:
        super().__init__(stop_reason(signum))
        self.signum = signum

    def __str__(self) -> str:
        return str(self.args[0])


@dataclass
class StopState:
    """What one ``stop_on_signals`` block has seen; the handler's only state."""

    stopping: bool = False
    """A stop has been delivered (or is pending): later signals are ignored."""
    signum: int | None = None
    """The signal that stopped the station, if any."""
    held: int = 0
    """Depth of ``held()`` sections: a stop arriving inside waits for the outermost to end."""
    pending: bool = False
    """A stop arrived inside a held section and is yet to be raised."""

    @property
    def reason(self) -> str | None:
        return None if self.signum is None else stop_reason(self.signum)


_active: StopState | None = None
"""The innermost active ``stop_on_signals`` block (signals are process-wide: one at a time)."""

_Handler = Callable[[int, FrameType | None], object] | int | None


@contextmanager
def stop_on_signals(signals: tuple[signal.Signals, ...] = STOP_SIGNALS) -> Iterator[StopState]:
    """Within the block, the first SIGINT/SIGTERM raises ``Stopped``; later ones are ignored.

    Signal handlers can only be installed from the main thread; called from
    any other thread the block changes nothing (the signals keep whatever
    handling the main thread gave them) and the state it yields stays empty.
    The handlers in place before the block are restored when it ends, however
    it ends.
    """
    global _active
    state = StopState()
    if threading.current_thread() is not threading.main_thread():
        yield state
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        name = signal.Signals(signum).name
        if state.stopping:
            # Raising now would cut short disabling the drive or recording the run.
            log.warning("%s received while the station is stopping: ignored until the drive "
                        "is disabled and the run recorded", name)
            return
        state.stopping, state.signum = True, signum
        if state.held:
            log.warning("%s received during a database write: stopping once it is committed",
                        name)
            state.pending = True
            return
        log.warning("%s received: stopping (the drive is disabled and the run recorded first)",
                    name)
        raise Stopped(signum)

    previous: dict[signal.Signals, _Handler] = {}
    outer = _active
    try:
        for sig in signals:
            previous[sig] = signal.signal(sig, handler)
        _active = state
        yield state
    finally:
        _active = outer
        for sig, old in previous.items():
            signal.signal(sig, old)


@contextmanager
def held() -> Iterator[None]:
    """A critical section no stop may interrupt; a stop arriving inside is raised after it.

    Outside ``stop_on_signals`` (or off the main thread, where no signal
    handler runs) this does nothing. The stop is raised only when the
    outermost section ends without an exception of its own: if the section
    failed, that failure is what the caller needs to see, and the station is
    stopping anyway, so later signals stay ignored.
    """
    state = _active
    if state is None or threading.current_thread() is not threading.main_thread():
        yield
        return
    state.held += 1
    try:
        yield
    finally:
        state.held -= 1
    if state.held == 0 and state.pending and state.signum is not None:
        state.pending = False
        raise Stopped(state.signum)
