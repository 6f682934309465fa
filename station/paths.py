"""Where the station keeps its files when nobody says otherwise.

``STATION_HOME`` (default ``~/.station``) holds the simulated units' EEPROM
state, truth files of simulated recordings, and by default the database and
run recordings. Tests point it at a temporary directory.
"""

from __future__ import annotations

import getpass
import os
from pathlib import Path

from station.storage import DbTarget, target_of

HOME_ENV = "STATION_HOME"
"""The environment variable naming the station's home."""
DB_ENV = "STATION_DB"
OPERATOR_ENV = "STATION_OPERATOR"


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


def database_path(explicit: str | Path | None = None) -> DbTarget:
    """``--db``, else ``STATION_DB``, else ``$STATION_HOME/station.db``: a SQLite file,
    or a line's PostgreSQL (a ``postgresql://`` URL)."""
    if explicit is not None:
        return target_of(str(explicit))
    from_env = os.environ.get(DB_ENV)
    return target_of(from_env) if from_env else default_database()


def default_operator() -> str:
    return os.environ.get(OPERATOR_ENV) or getpass.getuser()
