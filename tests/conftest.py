"""Guards every test: private station home, and nothing left running.

A calibration station that leaks a bus handle, a notifier thread or a database
connection per run falls over after a shift; so a test that leaves one behind
fails here.
"""

from __future__ import annotations

import os

# Small matrices on a busy 2-core machine: OpenBLAS's threads cost 30x more than they
# save. Set before numpy is first imported (pytest imports conftest first).
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

import sqlite3
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any, NoReturn

import can.interfaces.virtual as virtual_bus
import psycopg
import pytest

from station.testing.postgres import Cluster, server_binaries, throwaway_cluster
from tests.browser import chromium_binary

_GRACE_S = 2.0


def _open_virtual_queues() -> int:
    with virtual_bus.channels_lock:
        return sum(len(queues) for queues in virtual_bus.channels.values())


@pytest.fixture(autouse=True)
def station_home(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    """Each test gets its own STATION_HOME (EEPROM state, truth files, databases)."""
    home = tmp_path / "station-home"
    monkeypatch.setenv("STATION_HOME", str(home))
    monkeypatch.delenv("STATION_DB", raising=False)
    monkeypatch.delenv("STATION_BENCH", raising=False)
    return home


def _is_open(connection: sqlite3.Connection) -> bool:
    try:
        connection.total_changes  # noqa: B018 - any use of a closed connection raises
    except sqlite3.ProgrammingError:
        return False
    return True


@pytest.fixture(autouse=True)
def nothing_left_open(monkeypatch: pytest.MonkeyPatch) -> Iterator[None]:
    threads_before = set(threading.enumerate())
    queues_before = _open_virtual_queues()
    connections: list[sqlite3.Connection] = []
    connect = sqlite3.connect

    def tracked(*args: Any, **kwargs: Any) -> sqlite3.Connection:
        connection: sqlite3.Connection = connect(*args, **kwargs)
        connections.append(connection)
        return connection

    monkeypatch.setattr(sqlite3, "connect", tracked)
    servers: list[psycopg.Connection[Any]] = []
    connect_server = psycopg.connect

    def tracked_server(*args: Any, **kwargs: Any) -> psycopg.Connection[Any]:
        connection: psycopg.Connection[Any] = connect_server(*args, **kwargs)
        servers.append(connection)
        return connection

    monkeypatch.setattr(psycopg, "connect", tracked_server)
    yield
    left = [c for c in connections if _is_open(c)]
    for connection in left:
        connection.close()
    assert not left, f"{len(left)} SQLite connection(s) left open"
    open_servers = [c for c in servers if not c.closed]
    for server in open_servers:
        server.close()
    assert not open_servers, f"{len(open_servers)} PostgreSQL connection(s) left open"
    deadline = time.monotonic() + _GRACE_S
    while True:
        leaked = [t for t in threading.enumerate() if t not in threads_before and t.is_alive()]
        queues = _open_virtual_queues() - queues_before
        if (not leaked and queues <= 0) or time.monotonic() > deadline:
            break
        time.sleep(0.02)
    assert not leaked, f"threads left running: {[t.name for t in leaked]}"
    assert queues <= 0, f"{queues} virtual CAN bus handle(s) left open"


@pytest.fixture(scope="session")
def postgresql_binaries() -> Path:
    """The PostgreSQL server's binaries.

    Without them the tests that need a server are skipped, except under CI (``CI``
    set), whose set-up installs them: there a missing server is a failure.
    """
    binaries = server_binaries()
    if binaries is None:
        _missing("PostgreSQL's server binaries are not installed (Debian: postgresql)")
    return binaries


@pytest.fixture(scope="session")
def chromium() -> str:
    """Debian's chromium, to look at pages as a person does; skipped without it, except
    under CI, whose set-up installs it."""
    binary = chromium_binary()
    if binary is None:
        _missing("chromium is not installed (Debian: chromium)")
    return binary


def _missing(tool: str) -> NoReturn:
    """A tool the tests need: skipped on a developer's machine without it, a failure under
    CI (``CI`` set), whose set-up installs it."""
    if os.environ.get("CI"):
        pytest.fail(tool)
    pytest.skip(tool)


@pytest.fixture(scope="session")
def postgresql_cluster(postgresql_binaries: Path) -> Iterator[Cluster]:
    """A real PostgreSQL server for the session, on loopback; stopped at the end."""
    with throwaway_cluster(postgresql_binaries) as cluster:
        yield cluster


@pytest.fixture
def postgresql_url(postgresql_cluster: Cluster) -> Iterator[str]:
    """A fresh, empty database of the session's server."""
    with postgresql_cluster.database() as url:
        yield url
