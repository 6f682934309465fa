"""The throwaway PostgreSQL clusters of tests and benchmarks: an outage can be made and
ended, and a session killed outright does not leave its server running."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import psycopg
import pytest

from station.errors import DatabaseUnreachable
from station.pgstore import PostgresStore
from station.testing.postgres import (
    FOLDER_PREFIX,
    OWNER_FILE,
    remove_orphans,
    throwaway_cluster,
)


def test_a_stopped_server_is_unreachable_and_answers_again_once_started(
    postgresql_binaries: Path,
) -> None:
    with throwaway_cluster(postgresql_binaries) as cluster:
        with PostgresStore(cluster.url()) as store:
            version = store.schema_version
        cluster.stop()
        with pytest.raises(DatabaseUnreachable):
            PostgresStore(cluster.url())
        cluster.start()  # same port, same settings: the stations' URL still holds
        with PostgresStore(cluster.url()) as store:
            assert store.schema_version == version


_SESSION = """
import sys, time
from pathlib import Path
from station.testing.postgres import throwaway_cluster
with throwaway_cluster(Path(sys.argv[1])) as cluster:
    print(cluster.folder, cluster.url(), flush=True)
    time.sleep(600)
"""


def test_a_cluster_whose_session_was_killed_is_stopped_and_removed_by_the_next(
    postgresql_binaries: Path,
) -> None:
    session = subprocess.Popen([sys.executable, "-c", _SESSION, str(postgresql_binaries)],
                               stdout=subprocess.PIPE, text=True)
    try:
        assert session.stdout is not None
        folder_text, url = session.stdout.readline().split()
    finally:
        session.send_signal(signal.SIGKILL)  # no finally, no atexit: as a CI timeout does
        session.wait(timeout=30)
        if session.stdout is not None:
            session.stdout.close()
    folder = Path(folder_text)
    assert folder.name.startswith(FOLDER_PREFIX) and (folder / OWNER_FILE).exists()
    with psycopg.connect(url, connect_timeout=5):
        pass  # the orphan still serves
    assert folder in remove_orphans(folder.parent)
    assert not folder.exists()
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            psycopg.connect(url, connect_timeout=2).close()
        except psycopg.OperationalError:
            break
        time.sleep(0.2)
    else:
        pytest.fail("the orphan's server still answers")


def test_a_cluster_of_a_living_session_is_left_alone(tmp_path: Path) -> None:
    mine = tmp_path / f"{FOLDER_PREFIX}mine"
    mine.mkdir()
    (mine / OWNER_FILE).write_text(f"{os.getpid()}\n")
    stranger = tmp_path / f"{FOLDER_PREFIX}other"  # without an owner: not ours to judge
    stranger.mkdir()
    assert remove_orphans(tmp_path) == []
    assert mine.exists() and stranger.exists()
