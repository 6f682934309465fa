"""The station's side of a CANopen bench: which bus, the SYNC clock, and SDO/NMT plumbing.

The bench is whatever python-can can open (socketcan, PCAN, Kvaser, ... or
``virtual`` for the simulated bench), so the bus is described by data
(``BusConfig``) and opened in exactly one place (``open_network``), which always
releases the bus handle and the notifier thread: a station that leaks them per
run stops working after a shift.

The station is the SYNC producer (ICD.md §1). Two clocks exist because two
kinds of bench exist: a simulated bench lives in simulated time and must be
stepped in lockstep (``SteppedSync``: the next SYNC only once every device has
answered the previous one, as fast as the host allows), a real bench lives in
wall-clock time (``PeriodicSync``: the interface repeats SYNC by itself).
"""

from __future__ import annotations

import logging
import struct
import threading
import time
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import IntFlag
from types import MappingProxyType, TracebackType
from typing import Any, Self, TypeVar

import can
import canopen
from canopen.objectdictionary import ObjectDictionaryError, ODVariable
from canopen.sdo.exceptions import SdoAbortedError, SdoCommunicationError

from drivers.base import DeviceIdentity, retried
from station.cia301 import (
    ABORT_MEANINGS,
    NMT_COB_ID,
    SYNC_COB_ID,
    SYNC_COUNTER_OVERFLOW,
    TPDO1_COB_BASE,
    TPDO2_COB_BASE,
    NmtCommand,
    NmtState,
)
from station.errors import (
    BusFault,
    DeviceError,
    DeviceRebooted,
    DeviceTimeout,
    InputError,
    SdoAbort,
)

log = logging.getLogger(__name__)
_T = TypeVar("_T")

VIRTUAL_INTERFACE = "virtual"
"""python-can's in-process bus: the only interface the simulated bench uses."""
DEFAULT_CHANNEL = "station-sim"
DEFAULT_BITRATE = 1_000_000
DEFAULT_RECEIVE_POLL_S = 0.1
"""How long the notifier blocks per read; bounds how long closing a network takes."""

SYNC_PRODUCER = "SYNC producer"
"""How errors of the station's own SYNC production name their source."""
DEFAULT_SYNC_PERIOD_S = 0.001
DEFAULT_SYNC_TIMEOUT_S = 0.5
DEFAULT_MAX_MISSING_CYCLES = 20
_SUPERVISE_SLICE_S = 0.1


_RESERVED_BUS_KEYS = frozenset({"interface", "channel", "bitrate"})
_CIA301_MAX_SYNC_OVERFLOW = 240


@dataclass(frozen=True)
class BusConfig:
    """A python-can bus, described as data so that a bench file can name any interface.

    ``options`` are passed to ``can.Bus`` unchanged (e.g. ``fd``, ``app_name``,
    ``receive_own_messages``), so whatever python-can supports needs no code here.
    """

    interface: str = VIRTUAL_INTERFACE
    channel: str | int = DEFAULT_CHANNEL
    bitrate: int = DEFAULT_BITRATE
    options: Mapping[str, object] = field(default_factory=dict, hash=False)

    def __post_init__(self) -> None:
        if self.interface not in can.interfaces.VALID_INTERFACES:
            raise InputError(
                f"CAN interface {self.interface!r} is unknown to python-can; "
                f"known: {', '.join(sorted(can.interfaces.VALID_INTERFACES))}"
            )
        if isinstance(self.channel, bool) or not isinstance(self.channel, str | int):
            raise InputError(f"CAN channel must be a string or an integer, not {self.channel!r}")
        if isinstance(self.bitrate, bool) or not isinstance(self.bitrate, int) or self.bitrate <= 0:
            raise InputError(f"CAN bitrate must be a positive integer, not {self.bitrate!r}")
        clash = _RESERVED_BUS_KEYS.intersection(self.options)
        if clash:
            raise InputError(f"bus options may not repeat {sorted(clash)}")
        # A frozen config must not change behind its user's back through the mapping.
        object.__setattr__(self, "options", MappingProxyType(dict(self.options)))

    @classmethod
    def from_mapping(cls, data: Mapping[str, object]) -> BusConfig:
        """Read a bench file's bus section: python-can keys, anything unknown is an option."""
        interface = data.get("interface", VIRTUAL_INTERFACE)
        channel = data.get("channel", DEFAULT_CHANNEL)
        bitrate = data.get("bitrate", DEFAULT_BITRATE)
        if not isinstance(interface, str):
            raise InputError(f"CAN interface must be a string, not {interface!r}")
        if isinstance(channel, bool) or not isinstance(channel, str | int):
            raise InputError(f"CAN channel must be a string or an integer, not {channel!r}")
        if isinstance(bitrate, bool) or not isinstance(bitrate, int):
            raise InputError(f"CAN bitrate must be an integer, not {bitrate!r}")
        options = {k: v for k, v in data.items() if k not in _RESERVED_BUS_KEYS}
        return cls(interface=interface, channel=channel, bitrate=bitrate, options=options)

    @classmethod
    def from_python_can_config(
        cls, *, path: str | None = None, context: str | None = None
    ) -> BusConfig:
        """The bus python-can itself is configured for on this machine.

        A bench PC usually already names its adapter for python-can
        (``CAN_INTERFACE``/``CAN_CHANNEL``/``CAN_BITRATE``, ``~/.canrc``, a
        section chosen by ``context``); the station then needs no bus settings.
        """
        try:
            found = dict(can.util.load_config(path=path, context=context))
        except (can.CanInterfaceNotImplementedError, ValueError) as exc:
            # python-can says 'Unknown interface type "None"' when nothing is set.
            raise InputError(
                f"python-can configuration names no usable interface ({exc}); "
                "set CAN_INTERFACE or an 'interface' in ~/.canrc"
            ) from exc
        found.setdefault("bitrate", DEFAULT_BITRATE)
        if found.get("channel") is None:
            found["channel"] = DEFAULT_CHANNEL
        return cls.from_mapping(found)

    def describe(self) -> str:
        """How the bus is named in error messages and logs."""
        return f"CAN {self.interface}:{self.channel}"


class Taps(can.Listener):
    """Listeners that see every frame before canopen dispatches it.

    They sit first on the notifier, so the frame that lets the station move on
    (the last answer to a SYNC, counted by canopen's subscribers) has reached
    every tap by then: a recording closed as soon as its run returns still
    holds the run's last frame. Taps come and go between frames, never between
    two listeners' calls for one frame.
    """

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._taps: tuple[can.Listener, ...] = ()

    def add(self, *listeners: can.Listener) -> None:
        with self._lock:
            self._taps += listeners

    def remove(self, *listeners: can.Listener) -> None:
        with self._lock:
            self._taps = tuple(tap for tap in self._taps if tap not in listeners)

    def on_message_received(self, msg: can.Message) -> None:
        # The notifier's thread: one tuple read, no lock taken per frame.
        for tap in self._taps:
            tap.on_message_received(msg)


@contextmanager
def open_network(
    config: BusConfig | None = None,
    *,
    receive_poll_s: float = DEFAULT_RECEIVE_POLL_S,
    taps: Taps | None = None,
) -> Iterator[canopen.Network]:
    """A connected canopen network that is always disconnected on leaving, even on error.

    ``taps``, if given, see each frame before canopen does.
    """
    config = config if config is not None else BusConfig()
    options: dict[str, Any] = dict(config.options)
    try:
        bus = can.Bus(
            interface=config.interface, channel=config.channel, bitrate=config.bitrate, **options
        )
    except (can.CanError, OSError, ImportError, ValueError, TypeError) as exc:
        raise DeviceError(config.describe(), f"cannot open the CAN interface: {exc}") from exc
    network = canopen.Network(bus)
    # The notifier thread only notices a stop request between reads.
    network.NOTIFIER_CYCLE = receive_poll_s
    if taps is not None:
        # canopen types these as its own listener, but hands them to can.Notifier as is.
        network.listeners.insert(0, taps)  # type: ignore[arg-type]
    try:
        network.connect()
        yield network
    finally:
        try:
            network.disconnect()
        except Exception:
            log.exception("%s: error while disconnecting", config.describe())
        finally:
            bus.shutdown()


def send_nmt(network: canopen.Network, command: NmtCommand, node_id: int = 0) -> None:
    """Send one NMT command; node 0 addresses every node on the bus."""
    network.send_message(NMT_COB_ID, bytes((int(command), node_id)))


def set_operational(network: canopen.Network, *node_ids: int) -> None:
    """Let nodes send their PDOs (CiA 301: PDOs only flow in OPERATIONAL)."""
    for node_id in node_ids:
        send_nmt(network, NmtCommand.START_REMOTE_NODE, node_id)


def set_pre_operational(network: canopen.Network, *node_ids: int) -> None:
    """Silence nodes' PDOs while keeping their SDO servers reachable."""
    for node_id in node_ids:
        send_nmt(network, NmtCommand.ENTER_PRE_OPERATIONAL, node_id)


def sync_counter(index: int, overflow: int = SYNC_COUNTER_OVERFLOW) -> int:
    """Counter byte of the ``index``-th SYNC (0-based): 1..overflow, then 1 again."""
    return index % overflow + 1


def bench_tpdo_cob_ids(
    drive_node: int, sensor_node: int, *, drive_name: str = "drive", sensor_name: str = "sensor"
) -> dict[int, str]:
    """The TPDOs a bench answers each SYNC with (ICD.md §2, §3), and who sends each."""
    return {
        TPDO1_COB_BASE + sensor_node: sensor_name,
        TPDO1_COB_BASE + drive_node: drive_name,
        TPDO2_COB_BASE + drive_node: drive_name,
    }


class ErrorClass(IntFlag):
    """SocketCAN's error classes (linux/can/error.h), carried in an error frame's ID."""

    TX_TIMEOUT = 0x001
    LOST_ARBITRATION = 0x002
    CONTROLLER = 0x004
    PROTOCOL = 0x008
    TRANSCEIVER = 0x010
    NO_ACK = 0x020
    BUS_OFF = 0x040
    BUS_ERROR = 0x080
    RESTARTED = 0x100


class ControllerProblem(IntFlag):
    """Data byte 1 of a CONTROLLER error frame."""

    RX_OVERFLOW = 0x01
    TX_OVERFLOW = 0x02
    RX_WARNING = 0x04
    TX_WARNING = 0x08
    RX_PASSIVE = 0x10
    TX_PASSIVE = 0x20
    ACTIVE = 0x40


class BusMonitor(can.Listener):
    """What the interface says about the bus itself: error frames, error-passive, bus-off.

    canopen drops error frames before any callback sees them, so the station
    listens for them itself. Error frames alone cost nothing but retransmissions
    (CAN's CRC and automatic repeat keep the data sound; a frame that is lost
    anyway leaves a hole the analysis sees), so they are counted and reported.
    Bus-off is different: the controller has left the bus, and every frame the
    station believed sent may be gone; ``check`` then raises ``BusFault``.
    """

    def __init__(self, bus_name: str) -> None:
        self._bus_name = bus_name
        self._lock = threading.Lock()
        self.error_frames = 0
        self.passive = False
        self._bus_off = False

    def on_message_received(self, msg: can.Message) -> None:
        if not msg.is_error_frame:
            return
        classes = ErrorClass(msg.arbitration_id & 0x1FF)
        problems = ControllerProblem(msg.data[1]) if len(msg.data) > 1 else ControllerProblem(0)
        with self._lock:
            self.error_frames += 1
            if classes & ErrorClass.BUS_OFF:
                self._bus_off = True
            if classes & ErrorClass.CONTROLLER and problems & (
                ControllerProblem.RX_PASSIVE | ControllerProblem.TX_PASSIVE
            ):
                self.passive = True
        if classes & ErrorClass.BUS_OFF:
            log.error("%s: the CAN controller reports bus-off", self._bus_name)

    def check(self) -> None:
        with self._lock:
            bus_off, count = self._bus_off, self.error_frames
        if bus_off:
            raise BusFault(self._bus_name, f"bus-off after {count} error frames: frames sent "
                           "since may be lost; check termination, wiring and bit rate")


class SyncClock(ABC):
    """The station's SYNC producer: the time base of every sample on the bench.

    A supervisor (``supervise``) is called while the clock runs, at least every
    0.1 s of waiting and after every ``advance``, so a silent device, a reboot or
    a bus-off stops a run within moments instead of after its timeouts.
    """

    _supervisor: Callable[[], None] | None = None

    def supervise(self, check: Callable[[], None] | None) -> None:
        """Call ``check`` (which raises to stop the run) while the clock runs."""
        self._supervisor = check

    def _supervise(self) -> None:
        if self._supervisor is not None:
            self._supervisor()

    @property
    @abstractmethod
    def period_s(self) -> float:
        """Time between SYNCs as the devices see it (simulated or wall-clock)."""

    @property
    @abstractmethod
    def cycles(self) -> int:
        """SYNC frames sent so far."""

    @abstractmethod
    def advance(self, cycles: int) -> None:
        """Block until ``cycles`` more SYNC cycles have passed."""

    @abstractmethod
    def close(self) -> None:
        """Stop producing SYNC; safe to call twice."""

    def __enter__(self) -> Self:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()


def _check_overflow(overflow: int) -> None:
    if not 2 <= overflow <= _CIA301_MAX_SYNC_OVERFLOW:
        raise InputError(f"SYNC counter overflow must be 2..240 (CiA 301), not {overflow}")


class SteppedSync(SyncClock):
    """Lockstep SYNC for devices that live in simulated time.

    SYNC n+1 goes out as soon as every expected TPDO has answered SYNC n, so the
    bench runs as fast as the host allows and no sample is ever skipped by
    scheduling jitter. Frames are counted per COB-ID against SYNCs sent, so
    that a slow answer cannot shift every later cycle by one (which would make
    a recording put samples one SYNC late): a frame that misses its deadline
    is counted in ``missed`` but still awaited; only once the device answers a
    later SYNC while the gap persists is the missing frame taken as lost. A
    COB-ID silent for ``max_missing_cycles`` cycles in a row means its device
    is gone: ``DeviceTimeout`` names it.

    Within one ``advance`` the next SYNC is sent by the thread that receives
    the cycle's last frame, not by the caller: a thread hand-off per cycle is
    the largest cost of a simulated bench, and this saves one of three. The
    caller only supervises: it restarts the chain after a stall.
    """

    def __init__(
        self,
        network: canopen.Network,
        *,
        period_s: float = DEFAULT_SYNC_PERIOD_S,
        expected_cob_ids: Mapping[int, str],
        timeout_s: float = DEFAULT_SYNC_TIMEOUT_S,
        max_missing_cycles: int = DEFAULT_MAX_MISSING_CYCLES,
        counter_overflow: int = SYNC_COUNTER_OVERFLOW,
    ) -> None:
        if period_s <= 0 or timeout_s <= 0:
            raise InputError("SYNC period and timeout must be positive")
        if max_missing_cycles < 1:
            raise InputError("max_missing_cycles must be at least 1")
        if not expected_cob_ids:
            raise InputError("lockstep SYNC needs at least one expected COB-ID")
        _check_overflow(counter_overflow)
        if network.bus is None:
            raise DeviceError(SYNC_PRODUCER, "the network is not connected")
        self._network = network
        self._period_s = period_s
        self._timeout_s = timeout_s
        self._max_missing = max_missing_cycles
        self._devices = dict(expected_cob_ids)
        # Prebuilt frames: one per counter value, no allocation per cycle.
        self._frames = [
            can.Message(
                arbitration_id=SYNC_COB_ID,
                data=bytes((sync_counter(k, counter_overflow),)),
                is_extended_id=False,
            )
            for k in range(counter_overflow)
        ]
        self._lock = threading.Lock()
        self._progress = threading.Condition(self._lock)
        self._sent = 0
        self._target = 0
        self._completed = 0
        self._completed_at_stall = 0
        self._cycle_started = 0.0
        self._failure: DeviceError | None = None
        self._outstanding = 0
        self._received = dict.fromkeys(self._devices, 0)
        self._received_at_sync = dict.fromkeys(self._devices, 0)
        self._written_off = dict.fromkeys(self._devices, 0)
        self._missed = dict.fromkeys(self._devices, 0)
        self._consecutive = dict.fromkeys(self._devices, 0)
        self._any_consecutive = False
        self._closed = False
        for cob_id in self._devices:
            network.subscribe(cob_id, self._on_frame)

    @property
    def period_s(self) -> float:
        return self._period_s

    @property
    def cycles(self) -> int:
        return self._sent

    @property
    def missed(self) -> dict[int, int]:
        """Per COB-ID, the cycles in which its frame did not come within the timeout."""
        with self._lock:
            return dict(self._missed)

    @property
    def received(self) -> dict[int, int]:
        """Per COB-ID, the frames received since the clock started."""
        with self._lock:
            return dict(self._received)

    def _on_frame(self, can_id: int, data: bytearray, timestamp: float) -> None:
        # Runs on the notifier thread for every TPDO: keep it to integer work.
        frames: list[can.Message] = []
        with self._lock:
            received = self._received[can_id] + 1
            self._received[can_id] = received
            written_off = self._written_off[can_id]
            accounted = received + written_off
            if accounted == self._sent:
                self._outstanding -= 1
                if self._outstanding == 0:
                    self._complete_and_chain(frames)
            elif accounted > self._sent and written_off > 0:
                # A frame we had given up on arrived late: it was not lost after all.
                self._written_off[can_id] = written_off - 1
        for frame in frames:
            try:
                self._send(frame)
            except DeviceError as exc:
                with self._progress:
                    self._failure = exc
                    self._progress.notify_all()
                return

    def _begin_cycle(self) -> can.Message:
        """Account for one more SYNC (lock held) and return the frame to send."""
        frame = self._frames[self._sent % len(self._frames)]
        self._sent += 1
        self._cycle_started = time.monotonic()
        self._received_at_sync.update(self._received)
        self._outstanding = sum(
            1
            for cob_id, received in self._received.items()
            if received + self._written_off[cob_id] < self._sent
        )
        return frame

    def _complete_and_chain(self, frames: list[can.Message]) -> None:
        """A cycle is complete (lock held): start the next one while the batch lasts.

        The supervising caller is woken only when the batch is over; waking it
        every cycle would cost the very thread hand-off chaining saves.
        """
        self._completed += 1
        self._chain(frames)
        if not frames and self._outstanding == 0:
            self._progress.notify_all()

    def _chain(self, frames: list[can.Message]) -> None:
        """Start the next cycle (lock held), unless the batch is over.

        A device ahead of the SYNCs (a frame too many) leaves nothing to wait
        for, so such a cycle completes as soon as it starts.
        """
        while self._sent < self._target:
            frames.append(self._begin_cycle())
            if self._outstanding:
                return
            self._completed += 1

    def _send(self, frame: can.Message) -> None:
        bus = self._network.bus
        if bus is None:
            raise DeviceError(SYNC_PRODUCER, "the network is disconnected")
        try:
            with self._network.send_lock:
                bus.send(frame)
        except can.CanError as exc:
            raise DeviceError(SYNC_PRODUCER, f"cannot send SYNC: {exc}") from exc

    def advance(self, cycles: int) -> None:
        if cycles < 0:
            raise InputError(f"cannot advance by {cycles} cycles")
        if self._closed:
            raise DeviceError(SYNC_PRODUCER, "the SYNC clock is closed")
        if self._network.bus is None:
            raise DeviceError(SYNC_PRODUCER, "the network is disconnected")
        if cycles == 0:
            return
        frames: list[can.Message] = []
        with self._lock:
            self._failure = None
            self._target = self._sent + cycles
            self._chain(frames)
        while True:
            for frame in frames:
                self._send(frame)
            frames = []
            if self._await_batch():
                self._supervise()
                return
            # Stalled: a frame did not come within the timeout.
            self._check_receiver()
            self._supervise()
            self._account_for_missing()
            with self._lock:
                if self._sent >= self._target:
                    return
                self._chain(frames)

    def _await_batch(self) -> bool:
        """Wait while the chain makes progress; True once the batch is done, False on a stall.

        A stall is the SYNC in flight still unanswered ``timeout_s`` after it
        was sent: the same deadline per SYNC as if the caller sent each one.
        """
        with self._progress:
            while True:
                if self._any_consecutive and self._completed != self._completed_at_stall:
                    # A cycle completed since the last stall: misses are not in a row.
                    self._clear_consecutive()
                if self._failure is not None:
                    raise self._failure
                if self._sent >= self._target and self._outstanding == 0:
                    return True
                remaining = self._cycle_started + self._timeout_s - time.monotonic()
                if remaining <= 0:
                    return False
                self._progress.wait(remaining)

    def _check_receiver(self) -> None:
        """A dead notifier thread also looks like silent devices: name the real cause."""
        try:
            self._network.check()
        except Exception as exc:
            raise DeviceError(SYNC_PRODUCER, f"CAN reception has stopped: {exc!r}") from exc

    def _clear_consecutive(self) -> None:
        """Lock held."""
        for cob_id in self._consecutive:
            self._consecutive[cob_id] = 0
        self._any_consecutive = False

    def _account_for_missing(self) -> None:
        gone: list[int] = []
        with self._lock:
            self._completed_at_stall = self._completed
            for cob_id, received in self._received.items():
                deficit = self._sent - received - self._written_off[cob_id]
                if deficit <= 0:
                    self._consecutive[cob_id] = 0
                elif received > self._received_at_sync[cob_id]:
                    # The device answered this SYNC, so the gap is older: those frames are lost.
                    self._written_off[cob_id] += deficit
                    self._consecutive[cob_id] = 0
                else:
                    # Nothing at all this cycle: late or gone; keep waiting for it.
                    self._missed[cob_id] += 1
                    self._consecutive[cob_id] += 1
                    self._any_consecutive = True
                    if self._consecutive[cob_id] >= self._max_missing:
                        gone.append(cob_id)
        if gone:
            cob_id = gone[0]
            raise DeviceTimeout(
                self._devices[cob_id],
                f"no frame 0x{cob_id:03X} for {self._max_missing} consecutive SYNCs "
                f"(timeout {self._timeout_s} s each)",
            )

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        for cob_id in self._devices:
            subscribers = self._network.subscribers.get(cob_id, [])
            if self._on_frame in subscribers:
                self._network.unsubscribe(cob_id, self._on_frame)


class PeriodicSync(SyncClock):
    """Wall-clock SYNC for real benches, repeated by the interface itself.

    The 240 counter values are handed to python-can's ``send_periodic`` as one
    sequence, so interfaces with hardware cyclic transmission (e.g. socketcan's
    BCM) keep the counter running without the host. The host cannot see each
    transmission, so ``cycles`` is derived from elapsed time since the start.
    """

    def __init__(
        self,
        network: canopen.Network,
        *,
        period_s: float = DEFAULT_SYNC_PERIOD_S,
        counter_overflow: int = SYNC_COUNTER_OVERFLOW,
    ) -> None:
        if period_s <= 0:
            raise InputError("SYNC period must be positive")
        _check_overflow(counter_overflow)
        bus = network.bus
        if bus is None:
            raise DeviceError(SYNC_PRODUCER, "the network is not connected")
        frames = [
            can.Message(
                arbitration_id=SYNC_COB_ID,
                data=bytes((sync_counter(k, counter_overflow),)),
                is_extended_id=False,
            )
            for k in range(counter_overflow)
        ]
        self._period_s = period_s
        self._closed = False
        self._final_cycles = 0
        try:
            self._task = bus.send_periodic(frames, period_s)
        except (can.CanError, ValueError, NotImplementedError) as exc:
            raise DeviceError(SYNC_PRODUCER, f"cannot start periodic SYNC: {exc}") from exc
        # Taken once transmission has started, so the estimate lags rather than leads.
        self._started = time.perf_counter()

    @property
    def period_s(self) -> float:
        return self._period_s

    @property
    def cycles(self) -> int:
        if self._closed:
            return self._final_cycles
        # The first SYNC leaves at start, one more every period.
        return int((time.perf_counter() - self._started) / self._period_s) + 1

    def advance(self, cycles: int) -> None:
        if cycles < 0:
            raise InputError(f"cannot advance by {cycles} cycles")
        if self._closed:
            raise DeviceError(SYNC_PRODUCER, "the SYNC clock is closed")
        target = self.cycles + cycles
        deadline = self._started + (target - 1) * self._period_s
        while (remaining := deadline - time.perf_counter()) > 0:
            time.sleep(min(remaining, _SUPERVISE_SLICE_S))
            self._supervise()
        self._supervise()

    def close(self) -> None:
        if self._closed:
            return
        self._final_cycles = self.cycles
        self._closed = True
        self._task.stop()


class HeartbeatWatch:
    """Last heartbeat of one node, fed by the RemoteNode's NMT heartbeat callback.

    Every heartbeat bumps a sequence number, and the number at which each state
    was last reported is kept, so a caller can wait for a state reported
    *after* it sent a command, even if a newer heartbeat already says
    otherwise (a boot-up frame is followed at once by PRE-OPERATIONAL).
    """

    def __init__(self, node: canopen.RemoteNode) -> None:
        self._cond = threading.Condition()
        self._last: float | None = None
        self._seq = 0
        self._seen_at: dict[int, int] = {}
        self._boots = 0
        node.nmt.add_heartbeat_callback(self._on_heartbeat)

    def _on_heartbeat(self, state: int) -> None:
        with self._cond:
            self._last = time.monotonic()
            self._seq += 1
            self._seen_at[state] = self._seq
            if state == NmtState.BOOT_UP:
                self._boots += 1
            self._cond.notify_all()

    @property
    def boots(self) -> int:
        """Boot-up frames seen: one more than expected means the node restarted by itself."""
        with self._cond:
            return self._boots

    def check(self, device: str, *, max_age_s: float, boots_expected: int) -> None:
        """Raise if the node fell silent or booted behind the station's back.

        Heartbeats are the bus's own liveness signal (ICD.md §1: every 100 ms);
        a boot-up frame the station did not cause is a power cycle or a
        watchdog reset, after which the node's RAM (trims under test, power
        state) is gone.
        """
        with self._cond:
            last, boots = self._last, self._boots
        if boots > boots_expected:
            raise DeviceRebooted(device, "sent a boot-up frame mid-run (power cycle or reset "
                                 "by itself): its RAM, trims under test included, is gone")
        if last is None:
            raise DeviceTimeout(device, "no heartbeat ever seen")
        age = time.monotonic() - last
        if age > max_age_s:
            raise DeviceTimeout(device, f"silent: last heartbeat {age:.2f} s ago "
                                f"(heartbeat consumer time {max_age_s} s)")

    @property
    def sequence(self) -> int:
        with self._cond:
            return self._seq

    def age_s(self) -> float | None:
        """Seconds since the last heartbeat, ``None`` if none was ever seen."""
        with self._cond:
            return None if self._last is None else time.monotonic() - self._last

    def wait_for(self, state: NmtState, *, after: int, timeout_s: float) -> bool:
        """Wait for a heartbeat reporting ``state`` newer than sequence ``after``."""
        deadline = time.monotonic() + timeout_s
        with self._cond:
            while self._seen_at.get(state, 0) <= after:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    return False
                self._cond.wait(remaining)
            return True


class SdoChannel:
    """Typed SDO reads and writes that fail only with station errors.

    Values are encoded with the data types of the device's EDS, and every
    failure keeps what a technician needs: the device's own abort code, or a
    timeout naming the device and the object.
    """

    def __init__(self, node: canopen.RemoteNode, device: str, timeout_s: float) -> None:
        self._node = node
        self._device = device
        node.sdo.RESPONSE_TIMEOUT = timeout_s

    @contextmanager
    def timeout(self, timeout_s: float) -> Iterator[None]:
        """A longer deadline for slow services (an EEPROM write takes its time)."""
        previous = self._node.sdo.RESPONSE_TIMEOUT
        self._node.sdo.RESPONSE_TIMEOUT = max(previous, timeout_s)
        try:
            yield
        finally:
            self._node.sdo.RESPONSE_TIMEOUT = previous

    def _variable(self, index: int, subindex: int) -> ODVariable:
        variable = self._node.object_dictionary.get_variable(index, subindex)
        if variable is None:
            raise DeviceError(
                self._device, f"object 0x{index:04X}:{subindex:02X} is missing from its EDS"
            )
        return variable

    def _where(self, index: int, subindex: int) -> str:
        return f"SDO 0x{index:04X}:{subindex:02X}"

    @contextmanager
    def _errors(self, index: int, subindex: int) -> Iterator[None]:
        """Turn every canopen/python-can failure of one transfer into a station error."""
        where = self._where(index, subindex)
        try:
            yield
        except SdoAbortedError as exc:
            raise SdoAbort(self._device, index, subindex, exc.code,
                           ABORT_MEANINGS.get(exc.code, "")) from exc
        except SdoCommunicationError as exc:
            raise DeviceTimeout(self._device, f"{where}: {exc}") from exc
        except ObjectDictionaryError as exc:
            raise DeviceError(self._device, f"{where}: bad answer: {exc}") from exc
        except can.CanError as exc:
            raise DeviceError(self._device, f"{where}: {exc}") from exc
        except RuntimeError as exc:
            # canopen's way of saying the node or network is no longer connected.
            raise DeviceError(self._device, f"{where}: not connected ({exc})") from exc

    def _retried(self, index: int, subindex: int, transfer: Callable[[], _T]) -> _T:
        """``transfer``, sent again (``drivers.base.retried``) while it times out."""

        def once() -> _T:
            with self._errors(index, subindex):
                return transfer()

        return retried(once, device=self._device, what=self._where(index, subindex),
                       unanswered=DeviceTimeout)

    def read(self, index: int, subindex: int = 0) -> int | float:
        variable = self._variable(index, subindex)
        raw = self._retried(index, subindex, lambda: self._node.sdo.upload(index, subindex))
        with self._errors(index, subindex):
            value = variable.decode_raw(raw)
        if isinstance(value, bool) or not isinstance(value, int | float):
            raise DeviceError(
                self._device, f"{self._where(index, subindex)} is not a number: {value!r}"
            )
        return value

    def read_int(self, index: int, subindex: int = 0) -> int:
        value = self.read(index, subindex)
        if not isinstance(value, int):
            raise DeviceError(self._device, f"{self._where(index, subindex)} is not an integer")
        return value

    def read_float(self, index: int, subindex: int = 0) -> float:
        return float(self.read(index, subindex))

    def _encode(self, index: int, subindex: int, value: int | float) -> bytes:
        variable = self._variable(index, subindex)
        try:
            return variable.encode_raw(value)
        except (ValueError, TypeError, struct.error, ObjectDictionaryError) as exc:
            raise InputError(
                f"{self._device}: {value!r} does not fit {self._where(index, subindex)}: {exc}"
            ) from exc

    def check(self, index: int, subindex: int, value: int | float) -> None:
        """Refuse, before any bus traffic, a value the object's data type cannot hold."""
        self._encode(index, subindex, value)

    def write(self, index: int, subindex: int, value: int | float) -> None:
        data = self._encode(index, subindex, value)
        self._retried(index, subindex, lambda: self._node.sdo.download(index, subindex, data))

    def identity(self) -> DeviceIdentity:
        """CiA 301 identity object 0x1018:01..04."""
        return DeviceIdentity(
            vendor_id=self.read_int(0x1018, 1),
            product_code=self.read_int(0x1018, 2),
            revision=self.read_int(0x1018, 3),
            serial_number=self.read_int(0x1018, 4),
        )


def check_alive(heartbeat: HeartbeatWatch, sdo: SdoChannel, device: str, *,
                max_age_s: float, boots_expected: int) -> None:
    """Raise if the node rebooted, or fell silent: a late heartbeat is confirmed first.

    Heartbeats are passive, so a host too busy to read the bus for a moment
    looks exactly like a dead node; one SDO request (retried as any) tells
    them apart before a good unit's run is thrown away.
    """
    try:
        heartbeat.check(device, max_age_s=max_age_s, boots_expected=boots_expected)
    except DeviceRebooted:
        raise
    except DeviceTimeout as late:
        try:
            sdo.read_int(0x1000)  # device type: every CiA 301 node has it
        except DeviceTimeout as silent:
            raise late from silent
        log.warning("%s: %s, but it answers SDO: its heartbeat is late, not gone", device, late)


def check_node_id(node_id: int, device: str) -> None:
    """CiA 301 node-IDs are 1..127; refuse anything else before touching the bus."""
    if isinstance(node_id, bool) or not isinstance(node_id, int) or not 1 <= node_id <= 127:
        raise InputError(f"{device}: node-ID must be 1..127, not {node_id!r}")


def attach_remote_node(
    network: canopen.Network,
    node_id: int,
    object_dictionary: canopen.ObjectDictionary,
    device: str,
) -> canopen.RemoteNode:
    """Add a RemoteNode for ``node_id``, refusing to silently replace another driver's."""
    check_node_id(node_id, device)
    if node_id in network.nodes:
        raise DeviceError(device, f"node {node_id} is already attached to this network")
    node = canopen.RemoteNode(node_id, object_dictionary)
    network.add_node(node)
    return node


def detach_remote_node(network: canopen.Network, node: canopen.RemoteNode) -> None:
    """Remove ``node`` from the network if it is still the one registered there."""
    node_id = node.id
    if node_id is not None and network.nodes.get(node_id) is node:
        del network[node_id]


def start_node(
    network: canopen.Network,
    node_id: int,
    heartbeat: HeartbeatWatch,
    device: str,
    *,
    timeout_s: float,
) -> None:
    """NMT start, confirmed by the node's own heartbeat (ICD.md §1: every 100 ms)."""
    seen = heartbeat.sequence
    set_operational(network, node_id)
    if not heartbeat.wait_for(NmtState.OPERATIONAL, after=seen, timeout_s=timeout_s):
        raise DeviceTimeout(device, f"no heartbeat reporting OPERATIONAL within {timeout_s} s")
