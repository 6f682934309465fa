"""A simulated unit keeps what was stored in it when the station process ends.

``station verify`` runs in a new process after ``station calibrate``; the
simulated drive must then report the trims the earlier process stored, and
not the ones it merely wrote.
"""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
import uuid
from pathlib import Path

from drivers.canbus import BusConfig, open_network
from drivers.canopen_drive import CanopenDrive
from station.core import Trims
from station.sim.bench import SimBench, SimBenchConfig

_FIRST_PROCESS = textwrap.dedent(
    """
    import sys, uuid
    from drivers.canbus import BusConfig, open_network
    from drivers.canopen_drive import CanopenDrive
    from station.core import Trims
    from station.sim.bench import SimBench, SimBenchConfig

    channel = f"first-{uuid.uuid4().hex}"
    with SimBench(SimBenchConfig(serial="SN321", channel=channel)), \\
            open_network(BusConfig(channel=channel)) as network, \\
            CanopenDrive(network) as drive:
        drive.write_trims(Trims(-121, -55, 8470, 11530))
        drive.store()
        drive.write_trims(Trims(10, 20, 9000, 11000))  # written, never stored
    """
)


def test_stored_trims_survive_into_a_new_station_process(station_home: Path) -> None:
    env = {**os.environ, "STATION_HOME": str(station_home)}
    subprocess.run([sys.executable, "-c", _FIRST_PROCESS], check=True, env=env, timeout=60)
    channel = f"second-{uuid.uuid4().hex}"
    with (
        SimBench(SimBenchConfig(serial="SN321", channel=channel)),
        open_network(BusConfig(channel=channel)) as network,
        CanopenDrive(network) as drive,
    ):
        assert drive.read_trims() == Trims(-121, -55, 8470, 11530)
