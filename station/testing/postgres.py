"""A throwaway PostgreSQL cluster for tests and benchmarks: its own data folder, on
loopback, gone afterwards.

Debian's server binaries (``/usr/lib/postgresql/<version>/bin``, the ``postgresql``
package) are used as they are; ``initdb`` refuses to run as root, so as root the server
runs as the ``postgres`` user the package creates. A test session switches durability
off (fsync would only slow it down); a benchmark of writes keeps it, as a line's server
would.

A session killed outright (SIGKILL, a CI timeout) cannot stop its server. Each cluster
notes the process it belongs to, and the next one started stops and removes the
clusters whose process is gone, so servers do not pile up on a developer's machine.
"""

from __future__ import annotations

import os
import pwd
import shutil
import socket
import subprocess
import tempfile
import uuid
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path

import psycopg

SERVER_USER = "postgres"
"""Who runs the server when the tests run as root."""
SUPERUSER = "station"
"""The cluster's superuser (trust authentication, loopback only)."""


def server_binaries() -> Path | None:
    """The newest installed server's binaries, or None."""
    found = sorted(Path("/usr/lib/postgresql").glob("*/bin/pg_ctl"),
                   key=lambda p: int(p.parts[-3]) if p.parts[-3].isdigit() else 0)
    if found:
        return found[-1].parent
    on_path = shutil.which("pg_ctl")
    return Path(on_path).parent if on_path else None


def _free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


FOLDER_PREFIX = "station-pg-"
OWNER_FILE = "owner.pid"
"""The process a cluster belongs to, in its folder."""


@dataclass(frozen=True)
class Cluster:
    port: int
    folder: Path
    binaries: Path
    as_server: bool  # the server runs as SERVER_USER (we are root)

    @property
    def data(self) -> Path:
        return self.folder / "data"

    def stop(self) -> None:
        """Stop the server as an outage would (fast shutdown: clients are cut off)."""
        _run([str(self.binaries / "pg_ctl"), "-D", str(self.data), "-m", "fast", "-w",
              "stop"], as_server=self.as_server)

    def start(self) -> None:
        """Start the server again, on the same port, with the options it had."""
        _run([str(self.binaries / "pg_ctl"), "-D", str(self.data), "-l",
              str(self.folder / "server.log"), "-w", "-t", "60", "start"],
             as_server=self.as_server)

    def url(self, database: str = "postgres") -> str:
        return f"postgresql://{SUPERUSER}@127.0.0.1:{self.port}/{database}"

    @contextmanager
    def database(self) -> Iterator[str]:
        """A new empty database's URL, dropped afterwards."""
        name = f"t_{uuid.uuid4().hex[:16]}"
        with psycopg.connect(self.url(), autocommit=True) as admin:
            admin.execute(f"CREATE DATABASE {name}")
        try:
            yield self.url(name)
        finally:
            with psycopg.connect(self.url(), autocommit=True) as admin:
                admin.execute(f"DROP DATABASE IF EXISTS {name} WITH (FORCE)")


def _run(command: list[str], *, as_server: bool) -> None:
    if as_server:
        command = ["runuser", "-u", SERVER_USER, "--", *command]
    done = subprocess.run(command, capture_output=True, text=True, timeout=120, check=False)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed ({done.returncode}): "
                           f"{done.stdout}{done.stderr}")


@contextmanager
def throwaway_cluster(binaries: Path, *, durable: bool = False) -> Iterator[Cluster]:
    """initdb, start on 127.0.0.1 at a free port, yield, stop, remove."""
    remove_orphans()
    as_server = os.geteuid() == 0
    folder = Path(tempfile.mkdtemp(prefix=FOLDER_PREFIX))
    (folder / OWNER_FILE).write_text(f"{os.getpid()}\n")
    data = folder / "data"
    if as_server:
        user = pwd.getpwnam(SERVER_USER)
        os.chown(folder, user.pw_uid, user.pw_gid)
    port = _free_port()
    cluster = Cluster(port, folder, binaries, as_server)
    started = False
    try:
        _run([str(binaries / "initdb"), "-D", str(data), "-U", SUPERUSER, "-A", "trust",
              "-E", "UTF8", "--no-locale", "--no-sync"], as_server=as_server)
        settings = {"listen_addresses": "127.0.0.1", "port": str(port),
                    "unix_socket_directories": str(folder)}
        if not durable:
            settings |= {"fsync": "off", "synchronous_commit": "off",
                         "full_page_writes": "off"}
        # In the cluster's own configuration, so a restart (Cluster.start) keeps them.
        with (data / "postgresql.conf").open("a") as conf:
            conf.writelines(f"{key} = '{value}'\n" for key, value in settings.items())
        cluster.start()
        started = True
        yield cluster
    finally:
        if started:
            with suppress(RuntimeError):  # stopped already (an outage a benchmark made)
                cluster.stop()
        shutil.rmtree(folder, ignore_errors=True)


def remove_orphans(tmp: Path | None = None) -> list[Path]:
    """Stop and remove the clusters whose owning process is gone; return their folders."""
    removed = []
    binaries = server_binaries()
    for folder in Path(tmp or tempfile.gettempdir()).glob(f"{FOLDER_PREFIX}*"):
        try:
            owner = int((folder / OWNER_FILE).read_text())
        except (OSError, ValueError):
            continue  # not ours, or being created
        if _alive(owner):
            continue
        data = folder / "data"
        if binaries is not None and (data / "postmaster.pid").exists():
            with suppress(RuntimeError, OSError):
                _run([str(binaries / "pg_ctl"), "-D", str(data), "-m", "immediate", "-w",
                      "stop"], as_server=os.geteuid() == 0)
        shutil.rmtree(folder, ignore_errors=True)
        removed.append(folder)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True  # someone else's, and running
    return True
