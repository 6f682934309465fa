"""A simulated bench and the station's network on a private virtual channel."""

from __future__ import annotations

import uuid
from collections.abc import Iterator
from pathlib import Path

import canopen
import pytest

from drivers.canbus import BusConfig, open_network
from station.sim.bench import SimBench, SimBenchConfig


@pytest.fixture
def channel() -> str:
    return f"test-drivers-{uuid.uuid4().hex}"


@pytest.fixture
def bench(channel: str, tmp_path: Path) -> Iterator[SimBench]:
    sim = SimBench(SimBenchConfig(serial="SN123", channel=channel), state_dir=tmp_path / "eeprom")
    sim.start()
    try:
        yield sim
    finally:
        sim.close()


@pytest.fixture
def network(bench: SimBench, channel: str) -> Iterator[canopen.Network]:
    with open_network(BusConfig(channel=channel)) as net:
        yield net
