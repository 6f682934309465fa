"""Bus configuration, network lifetime, NMT helpers and the two SYNC clocks.

These run against scripted responders on the virtual bus (not the simulated
bench), so that lateness, silence and counter wrap can be produced on purpose.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Callable, Iterator
from contextlib import contextmanager

import can
import canopen
import pytest

from drivers.canbus import (
    BusConfig,
    PeriodicSync,
    SteppedSync,
    bench_tpdo_cob_ids,
    open_network,
    send_nmt,
    set_operational,
    set_pre_operational,
    sync_counter,
)
from station.cia301 import SYNC_COB_ID, NmtCommand
from station.errors import DeviceTimeout, InputError

SENSOR_COB = 0x190
DRIVE_COB = 0x181

ON_TIME_S = 0.25
"""The deadline of frames a responder sends at once. Generous on purpose: on a loaded
2-core machine the responder's thread may wait tens of milliseconds for a core, and a
deadline it misses there would be taken for lateness the test did not make. Lateness
is made by withholding a frame until the next SYNC (``LATE``), never by sleeping."""

LATE = -1
"""What an ``answer`` returns for a frame answered only after the next SYNC, with it."""


def _channel() -> str:
    return f"test-canbus-{uuid.uuid4().hex}"


@contextmanager
def responder(channel: str, answer: Callable[[int, int], list[int]]) -> Iterator[list[int]]:
    """A fake bench: on each SYNC (n-th, counter c) it sends the COB-IDs ``answer(n, c)``;
    ``LATE`` in place of a COB-ID holds that frame back until the next SYNC, which the
    station sends only once the frame's deadline has passed: late for certain, however
    fast or slow the machine."""
    counters: list[int] = []
    held: list[int] = []
    with open_network(BusConfig(channel=channel)) as network:

        def on_sync(can_id: int, data: bytearray, timestamp: float) -> None:
            counters.append(data[0])
            for cob_id in held:
                network.send_message(cob_id, bytes(8))
            held.clear()
            wanted = answer(len(counters), data[0])
            if LATE in wanted:
                held.extend(c for c in wanted if c != LATE)
                return
            for cob_id in wanted:
                network.send_message(cob_id, bytes(8))

        network.subscribe(SYNC_COB_ID, on_sync)
        yield counters


def test_bus_config_from_mapping_passes_unknown_keys_to_python_can() -> None:
    config = BusConfig.from_mapping(
        {"interface": "pcan", "channel": "PCAN_USBBUS1", "bitrate": 500000, "fd": False}
    )
    assert (config.interface, config.channel, config.bitrate) == ("pcan", "PCAN_USBBUS1", 500000)
    assert dict(config.options) == {"fd": False}


def test_bus_config_defaults_to_the_virtual_interface_at_1_mbit() -> None:
    config = BusConfig.from_mapping({})
    assert (config.interface, config.bitrate) == ("virtual", 1_000_000)


@pytest.mark.parametrize(
    "mapping",
    [
        {"interface": "no-such-interface"},
        {"interface": "virtual", "bitrate": "fast"},
        {"interface": "virtual", "bitrate": -1},
        {"interface": "virtual", "channel": 1.5},
    ],
)
def test_bad_bus_section_is_refused_as_input_error(mapping: dict[str, object]) -> None:
    with pytest.raises(InputError):
        BusConfig.from_mapping(mapping)


def test_bus_options_cannot_override_interface_channel_or_bitrate() -> None:
    with pytest.raises(InputError, match="bitrate"):
        BusConfig(options={"bitrate": 250000})


def test_bus_config_options_cannot_be_changed_after_creation() -> None:
    options: dict[str, object] = {"receive_own_messages": False}
    config = BusConfig(options=options)
    options["receive_own_messages"] = True
    assert config.options["receive_own_messages"] is False
    with pytest.raises(TypeError):
        config.options["x"] = 1  # type: ignore[index]


def test_open_network_releases_bus_and_notifier_even_when_the_body_raises() -> None:
    threads_before = set(threading.enumerate())
    network_seen: list[canopen.Network] = []
    with (
        pytest.raises(RuntimeError, match="boom"),
        open_network(BusConfig(channel=_channel())) as network,
    ):
        network_seen.append(network)
        assert network.bus is not None
        raise RuntimeError("boom")
    assert network_seen[0].bus is None
    assert network_seen[0].notifier is not None and network_seen[0].notifier.stopped
    assert {t for t in threading.enumerate() if t.is_alive()} <= threads_before


def test_nmt_helpers_send_cia301_command_frames() -> None:
    channel = _channel()
    with (
        open_network(BusConfig(channel=channel)) as network,
        can.Bus(interface="virtual", channel=channel) as listener,
    ):
        set_operational(network, 1, 16)
        set_pre_operational(network, 16)
        send_nmt(network, NmtCommand.RESET_NODE)
        frames = [listener.recv(1.0) for _ in range(4)]
    assert [(m.arbitration_id, bytes(m.data)) for m in frames if m is not None] == [
        (0x000, b"\x01\x01"),
        (0x000, b"\x01\x10"),
        (0x000, b"\x80\x10"),
        (0x000, b"\x81\x00"),
    ]


def test_sync_counter_runs_1_to_240_then_starts_again_at_1() -> None:
    counters = [sync_counter(k) for k in range(481)]
    assert counters[0] == 1
    assert counters[239] == 240
    assert counters[240] == 1
    assert counters[480] == 1
    assert set(counters) == set(range(1, 241))


def test_bench_tpdo_cob_ids_follow_icd_node_offsets() -> None:
    assert bench_tpdo_cob_ids(1, 16) == {0x190: "sensor", 0x181: "drive", 0x281: "drive"}
    assert bench_tpdo_cob_ids(5, 20, drive_name="d") == {0x194: "sensor", 0x185: "d", 0x285: "d"}


def test_stepped_sync_waits_for_every_expected_frame_and_wraps_its_counter_on_the_wire() -> None:
    channel = _channel()
    with (
        responder(channel, lambda n, c: [SENSOR_COB, DRIVE_COB]) as counters,
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(network, expected_cob_ids={SENSOR_COB: "sensor", DRIVE_COB: "drive"}) as clock,
    ):
        clock.advance(245)
        assert clock.cycles == 245
        assert clock.missed == {SENSOR_COB: 0, DRIVE_COB: 0}
        # In lockstep every SYNC has been seen by the responder when advance returns.
        assert counters[:3] == [1, 2, 3]
        assert counters[238:243] == [239, 240, 1, 2, 3]
        assert len(counters) == 245


def test_stepped_sync_counts_a_late_frame_as_missed_and_then_keeps_in_step() -> None:
    channel = _channel()

    def answer(n: int, counter: int) -> list[int]:
        # SYNC 5 is answered after its deadline, with SYNC 6; later answers are slow
        # enough that only a clock really waiting for them keeps up.
        if n == 5:
            return [SENSOR_COB, LATE]
        time.sleep(0.002)
        return [SENSOR_COB]

    with (
        responder(channel, answer) as counters,
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(network, expected_cob_ids={SENSOR_COB: "sensor"},
                    timeout_s=ON_TIME_S) as clock,
    ):
        clock.advance(20)
        assert clock.missed == {SENSOR_COB: 1}
        clock.advance(30)
        # Lockstep: SYNC 50 was answered before advance returned, late frame included.
        assert clock.received == {SENSOR_COB: 50}
        assert len(counters) == clock.cycles == 50
        assert clock.missed == {SENSOR_COB: 1}


def test_stepped_sync_writes_off_a_frame_the_device_never_sent_and_carries_on() -> None:
    channel = _channel()
    with (
        responder(channel, lambda n, c: [] if n == 5 else [SENSOR_COB]),
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(network, expected_cob_ids={SENSOR_COB: "sensor"},
                    timeout_s=ON_TIME_S) as clock,
    ):
        clock.advance(40)
        assert clock.missed == {SENSOR_COB: 1}
        assert clock.received == {SENSOR_COB: 39}


def test_stepped_sync_raises_device_timeout_naming_the_silent_device() -> None:
    channel = _channel()
    with (
        responder(channel, lambda n, c: [SENSOR_COB]),
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(
            network,
            expected_cob_ids={SENSOR_COB: "sensor", DRIVE_COB: "drive"},
            timeout_s=ON_TIME_S,
            max_missing_cycles=3,
        ) as clock,
    ):
        with pytest.raises(DeviceTimeout, match=r"^drive: no frame 0x181") as raised:
            clock.advance(10)
        assert raised.value.device == "drive"
        assert clock.cycles == 3
        assert clock.missed == {SENSOR_COB: 0, DRIVE_COB: 3}


def test_stepped_sync_tolerates_sporadic_losses_below_the_limit() -> None:
    channel = _channel()
    with (
        responder(channel, lambda n, c: [] if n % 2 else [SENSOR_COB]),
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(
            network, expected_cob_ids={SENSOR_COB: "sensor"}, timeout_s=ON_TIME_S,
            max_missing_cycles=2
        ) as clock,
    ):
        clock.advance(10)
        assert clock.missed == {SENSOR_COB: 5}


def test_stepped_sync_unsubscribes_on_close_and_close_twice_is_harmless() -> None:
    with open_network(BusConfig(channel=_channel())) as network:
        clock = SteppedSync(network, expected_cob_ids={SENSOR_COB: "sensor"})
        assert SENSOR_COB in network.subscribers
        clock.close()
        clock.close()
        assert SENSOR_COB not in network.subscribers


def test_stepped_sync_refuses_an_empty_expectation() -> None:
    with open_network(BusConfig(channel=_channel())) as network, pytest.raises(InputError):
        SteppedSync(network, expected_cob_ids={})


def test_periodic_sync_repeats_the_counter_sequence_in_wall_clock_time() -> None:
    channel = _channel()
    with (
        open_network(BusConfig(channel=channel)) as network,
        can.Bus(interface="virtual", channel=channel) as listener,
    ):
        clock = PeriodicSync(network, period_s=0.001, counter_overflow=4)
        started = time.perf_counter()
        clock.advance(30)
        elapsed = time.perf_counter() - started
        # The virtual bus sends from a host thread, which a loaded machine may
        # starve for a while: wait for the frames (a generous 10 s, not a
        # speed limit) rather than counting what arrived by a fixed moment.
        counters: list[int] = []
        deadline = time.monotonic() + 10.0
        while len(counters) < 30 and time.monotonic() < deadline:
            frame = listener.recv(0.1)
            if frame is not None:
                assert frame.arbitration_id == SYNC_COB_ID
                counters.append(frame.data[0])
        cycles = clock.cycles
        clock.close()
        clock.close()
    assert elapsed >= 0.029
    assert counters == [1, 2, 3, 4] * 7 + [1, 2]
    assert cycles >= 30


def test_sync_counter_overflow_outside_cia301_range_is_refused() -> None:
    with open_network(BusConfig(channel=_channel())) as network, pytest.raises(InputError):
        PeriodicSync(network, counter_overflow=241)


def test_bus_can_come_from_python_cans_own_configuration(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("CAN_INTERFACE", "virtual")
    monkeypatch.setenv("CAN_CHANNEL", "bench-7")
    monkeypatch.setenv("CAN_BITRATE", "500000")
    config = BusConfig.from_python_can_config(path="/nonexistent/canrc")
    assert (config.interface, config.channel, config.bitrate) == ("virtual", "bench-7", 500000)


def test_python_can_configuration_without_interface_is_an_input_error(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    for name in ("CAN_INTERFACE", "CAN_CHANNEL", "CAN_BITRATE", "CAN_CONFIG"):
        monkeypatch.delenv(name, raising=False)
    monkeypatch.setenv("HOME", "/nonexistent")
    with pytest.raises(InputError, match="names no usable interface"):
        BusConfig.from_python_can_config(path="/nonexistent/canrc")


def test_scattered_late_frames_in_one_long_batch_are_not_taken_for_a_silent_device() -> None:
    channel = _channel()

    def answer(n: int, counter: int) -> list[int]:
        # Every tenth SYNC is answered after the deadline: a miss, but never two in a row.
        return [SENSOR_COB, LATE] if n % 10 == 5 else [SENSOR_COB]

    with (
        responder(channel, answer),
        open_network(BusConfig(channel=channel)) as network,
        SteppedSync(
            network,
            expected_cob_ids={SENSOR_COB: "sensor"},
            timeout_s=ON_TIME_S,
            max_missing_cycles=2,
        ) as clock,
    ):
        clock.advance(60)
        assert clock.missed == {SENSOR_COB: 6}
        assert clock.received == {SENSOR_COB: 60}
