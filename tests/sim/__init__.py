"""A minimal station side for testing the simulated bench over the virtual bus.

Deliberately independent of the station's own drivers (written separately):
plain canopen ``RemoteNode``s built from the same EDS files, a listener that
keeps every frame, and a lockstep SYNC producer.
"""

from __future__ import annotations

import threading
import time
import uuid
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, replace
from pathlib import Path

import can
import canopen

from drivers.eds import DeviceKind, load_od
from station.sim.bench import SimBench, SimBenchConfig

SYNC = 0x080
WAIT_S = 2.0


@dataclass(frozen=True)
class Frame:
    cob_id: int
    data: bytes
    timestamp: float


class _Keeper(can.Listener):
    """Keeps every frame the station sees, and wakes whoever waits for more.

    TPDO frames wake the waiter only once as many as it wants have arrived:
    waking it for each of them would cost the lockstep loop a thread switch per frame.
    """

    def __init__(self, tpdo_ids: tuple[int, ...]) -> None:
        self.frames: list[Frame] = []
        self.arrived = threading.Condition()
        self.tpdo_ids = frozenset(tpdo_ids)
        self.tpdos_seen = 0
        self.tpdos_wanted = 0

    def on_message_received(self, msg: can.Message) -> None:
        with self.arrived:
            self.frames.append(Frame(msg.arbitration_id, bytes(msg.data), time.monotonic()))
            if msg.arbitration_id in self.tpdo_ids:
                self.tpdos_seen += 1
                if self.tpdos_seen < self.tpdos_wanted:
                    return
            self.arrived.notify_all()

    def stop(self) -> None:
        """Nothing to release."""


class Station:
    """Station side: an NMT master, SDO clients for both devices, a SYNC producer."""

    def __init__(self, bench: SimBench) -> None:
        config = bench.config
        self.bench = bench
        self.config = config
        bus = can.Bus(interface="virtual", channel=config.channel, receive_own_messages=False)
        self.network = canopen.Network(bus)
        self.network.NOTIFIER_CYCLE = 0.05
        self.keeper = _Keeper(self.tpdo_ids)
        self.network.listeners.append(self.keeper)  # type: ignore[arg-type]
        self.network.connect()
        self.drive = self.network.add_node(
            config.drive_node, load_od(DeviceKind.DRIVE, config.drive_node)
        )
        self.sensor = self.network.add_node(
            config.sensor_node, load_od(DeviceKind.SENSOR, config.sensor_node)
        )
        self._counter = 0

    @property
    def tpdo_ids(self) -> tuple[int, int, int]:
        """Sensor TPDO1, drive TPDO1, drive TPDO2: the order frames follow a SYNC."""
        return (
            0x180 + self.config.sensor_node,
            0x180 + self.config.drive_node,
            0x280 + self.config.drive_node,
        )

    def nmt(self, command: int, node: int = 0) -> None:
        self.network.send_message(0, bytes([command, node]))

    def start_all(self) -> None:
        """NMT start (broadcast), confirmed by an SDO round trip to each device."""
        self.nmt(0x01)
        # An SDO answer proves each device has handled the NMT command before it.
        self.drive.sdo.upload(0x1000, 0)
        self.sensor.sdo.upload(0x1000, 0)

    def enable(self) -> None:
        """CiA 402: shutdown, switch on, enable operation."""
        for controlword in (0x06, 0x07, 0x0F):
            self.drive.sdo[0x6040].raw = controlword

    def sync(self, expect: int = 3) -> list[Frame]:
        """Send one SYNC and return the ``expect`` TPDO frames that answer it."""
        keeper = self.keeper
        self._counter = self._counter % 240 + 1
        target = self.bench.sync_count + 1
        with keeper.arrived:
            start = len(keeper.frames)
            keeper.tpdos_wanted = keeper.tpdos_seen + expect
        self.network.send_message(SYNC, bytes([self._counter]))
        deadline = time.monotonic() + WAIT_S
        with keeper.arrived:
            while keeper.tpdos_seen < keeper.tpdos_wanted or self.bench.sync_count < target:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    raise TimeoutError(f"SYNC answered with too few of {expect} TPDOs")
                keeper.arrived.wait(min(remaining, 0.005))
            return [f for f in keeper.frames[start:] if f.cob_id in keeper.tpdo_ids]

    def run(self, cycles: int, expect: int = 3) -> list[list[Frame]]:
        return [self.sync(expect) for _ in range(cycles)]

    def settle(self) -> None:
        """Return once the bench has handled everything sent so far (SDO goes after it)."""
        self.drive.sdo.upload(0x1000, 0)

    def wait_for(self, cob_id: int, count: int, since: int, timeout: float = WAIT_S) -> list[Frame]:
        deadline = time.monotonic() + timeout
        with self.keeper.arrived:
            while True:
                got = [f for f in self.keeper.frames[since:] if f.cob_id == cob_id]
                remaining = deadline - time.monotonic()
                if len(got) >= count or remaining <= 0:
                    return got
                self.keeper.arrived.wait(remaining)

    def close(self) -> None:
        self.network.disconnect()


def unique_config(**changes: object) -> SimBenchConfig:
    """A bench configuration on a channel of its own, so tests never share a bus."""
    base = SimBenchConfig(channel=f"test-sim-{uuid.uuid4().hex}")
    return replace(base, **changes)  # type: ignore[arg-type]


@contextmanager
def running(state_dir: Path, **changes: object) -> Iterator[tuple[SimBench, Station]]:
    """A started bench and a connected station; both shut down afterwards."""
    with SimBench(unique_config(**changes), state_dir=state_dir) as bench:
        station = Station(bench)
        try:
            yield bench, station
        finally:
            station.close()
