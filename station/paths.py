"""Where the station keeps its files when nobody says otherwise.

``STATION_HOME`` (default ``~/.station``) holds the simulated units' EEPROM
state, truth files of simulated recordings, and by default the database and
run recordings. Tests point it at a temporary directory.
"""

from __future__ import annotations

import os
from pathlib import Path

HOME_ENV = "STATION_HOME"
"""The environment variable naming the station's home."""


def station_home() -> Path:
    return Path(os.environ.get(HOME_ENV, Path.home() / ".station")).expanduser()


def default_database() -> Path:
    """The results database when neither ``--db`` nor ``STATION_DB`` names one."""
    return station_home() / "station.db"


def sim_state_dir() -> Path:
    """EEPROM images of simulated units, one file per serial."""
    return station_home() / "sim" / "eeprom"


def truth_dir() -> Path:
    """Truth files of simulated recordings, kept away from the recordings."""
    return station_home() / "truth"
