"""Who runs an open run, and whether that process is provably gone.

A run is recorded the moment it begins, so a station killed mid-run (``kill -9``, power
loss) leaves an open run behind. Each open run names its owner process (host, boot,
pid, start time, pid namespace); the next run begun on the same host finishes as
aborted those whose process this machine can prove has ended, and leaves alone every
run it cannot judge (another host, another boot id unknown, another container). Both
stores (``station.store``, ``station.pgstore``) use it; only this module reads
``/proc``. See ``db/README.md``, "Interrupted runs".
"""

from __future__ import annotations

import json
import logging
import os
import socket
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from station.runs import Verdict

log = logging.getLogger(__name__)

_BOOT_ID = Path("/proc/sys/kernel/random/boot_id")
_OWN_PID_NAMESPACE = Path("/proc/self/ns/pid")
_ZOMBIE_STATES = frozenset("ZX")  # exited (or being reaped): it will never write again


@dataclass(frozen=True)
class RunOwner:
    """The process that began an open run: enough to tell later whether it still runs.

    A pid alone is not enough: after a reboot or enough process churn it names
    another process. ``start_time`` (clock ticks after boot, field 22 of
    ``/proc/<pid>/stat``) tells a reused pid apart, ``boot_id`` a reboot, and
    ``pid_ns`` a process in another container, whose pids mean nothing here.
    ``None`` where Linux did not tell (not Linux, /proc not mounted): such an
    owner is never judged gone, because nothing proves it.
    """

    host: str
    pid: int
    boot_id: str | None = None
    start_time: int | None = None
    pid_ns: str | None = None

    def to_json(self) -> str:
        return json.dumps(
            {"host": self.host, "boot_id": self.boot_id, "pid": self.pid,
             "start_time": self.start_time, "pid_ns": self.pid_ns},
            separators=(",", ":"),
        )

    @classmethod
    def from_json(cls, text: str | None) -> RunOwner | None:
        """The owner a row names; None when the row names none or nothing readable.

        A row written before migration 0002, or edited by hand into nonsense,
        must not stop the next run from beginning: it is only left alone.
        """
        if text is None:
            return None
        try:
            doc = json.loads(text)
        except ValueError:
            return None
        if not isinstance(doc, dict):
            return None
        host, pid = doc.get("host"), doc.get("pid")
        boot_id, start_time, pid_ns = doc.get("boot_id"), doc.get("start_time"), doc.get("pid_ns")
        if not isinstance(host, str) or type(pid) is not int:
            return None
        return cls(
            host=host,
            pid=pid,
            boot_id=boot_id if isinstance(boot_id, str) else None,
            start_time=start_time if type(start_time) is int else None,
            pid_ns=pid_ns if isinstance(pid_ns, str) else None,
        )


@dataclass(frozen=True)
class ProcessInfo:
    """What this machine says about a pid that exists."""

    start_time: int | None
    """Field 22 of ``/proc/<pid>/stat``; None when it could not be read."""
    ended: bool = False
    """The process has exited and waits to be reaped (a zombie): it can write nothing more."""


ProcessProbe = Callable[[int], ProcessInfo | None]
"""Look a pid up on this machine: None when no such process exists."""


def _read_text(path: Path) -> str | None:
    """A small /proc file, stripped; None when unreadable or empty.

    Not strict about the encoding: a process name may hold any bytes, and the
    numbers around it are what is read.
    """
    try:
        return path.read_bytes().decode("ascii", errors="replace").strip() or None
    except OSError:
        return None


def _stat_fields(pid: int) -> list[str] | None:
    """``/proc/<pid>/stat`` from field 3 (state) on; None when unreadable.

    Field 2 is the command name in parentheses, which may itself hold spaces
    and parentheses: the fields start after the last ``)``.
    """
    text = _read_text(Path(f"/proc/{pid}/stat"))
    if text is None or ")" not in text:
        return None
    return text.rsplit(")", 1)[1].split()


def probe_process(pid: int) -> ProcessInfo | None:
    """This machine's answer about ``pid``: gone (None), or its start time and state.

    ``kill(pid, 0)`` decides existence (PermissionError: it exists, another
    user's), so a ``/proc`` mounted with ``hidepid`` cannot make a live
    station look dead; ``/proc`` then gives the start time when it can.
    """
    if pid <= 0:
        return None
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None
    except OSError:
        pass  # EPERM: it exists
    stat = _stat_fields(pid)
    if stat is None or len(stat) < 20:
        return ProcessInfo(start_time=None)
    try:
        start_time = int(stat[19])  # field 22; stat[0] is field 3
    except ValueError:
        start_time = None
    return ProcessInfo(start_time=start_time, ended=stat[0] in _ZOMBIE_STATES)


def current_owner() -> RunOwner:
    """This process, as a run it begins records its owner."""
    pid = os.getpid()
    me = probe_process(pid)
    try:
        pid_ns: str | None = os.readlink(_OWN_PID_NAMESPACE)
    except OSError:
        pid_ns = None
    return RunOwner(
        host=socket.gethostname(),
        pid=pid,
        boot_id=_read_text(_BOOT_ID),
        start_time=None if me is None else me.start_time,
        pid_ns=pid_ns,
    )


def why_gone(owner: RunOwner, here: RunOwner, probe: ProcessProbe) -> str | None:
    """Why the process ``owner`` names has provably ended, seen from ``here``; else None.

    Only proof counts: finishing a run whose station is still measuring would
    make it unrecordable (finished runs are final). So another host (whose
    processes this machine cannot see; a WAL database is only shared on one
    machine, so that is a copied file), an unknown boot, another pid namespace
    or a pid whose start time cannot be compared all leave the run open.
    """
    if owner.host != here.host or owner.boot_id is None or here.boot_id is None:
        return None
    if owner.boot_id != here.boot_id:
        return "the machine has restarted since"
    if owner.pid_ns is None or owner.pid_ns != here.pid_ns:
        return None
    info = probe(owner.pid)
    if info is None:
        return "the process no longer exists"
    if info.ended:
        # Whoever holds the pid has ended: the owner, or a later process after the owner.
        return "the process has exited"
    if (owner.start_time is not None and info.start_time is not None
            and info.start_time != owner.start_time):
        return "its pid now belongs to another process"
    return None


@dataclass(frozen=True)
class InterruptedRun:
    """An open run whose station process was found gone, and finished as aborted."""

    run_id: int
    serial: str
    owner: RunOwner
    reason: str

    def finish_values(self, finished_at: str) -> dict[str, object]:
        """The row's columns it is finished with (``utc_iso`` time)."""
        return {"run_id": self.run_id, "verdict": Verdict.ABORTED.value,
                "reason": self.reason, "finished_at": finished_at}


def interrupted_runs(gone: Iterable[tuple[int, str, RunOwner, str]], found_at_run: int
                     ) -> list[InterruptedRun]:
    """The runs ``gone_owners`` found, each with the reason it is finished with."""
    return [InterruptedRun(run_id, serial, owner, interrupted_reason(owner, why, found_at_run))
            for run_id, serial, owner, why in gone]


def log_interrupted(runs: Iterable[InterruptedRun]) -> None:
    for found in runs:
        log.warning("run %d of %s marked aborted: %s", found.run_id, found.serial,
                    found.reason)


def interrupted_reason(owner: RunOwner, why: str, found_at_run: int) -> str:
    """The reason an interrupted run is finished with: who, where, how it was found."""
    return (
        f"interrupted: station process {owner.pid} on host {owner.host} ended without "
        f"finishing the run ({why}; found at the start of run {found_at_run})"
    )


def gone_owners(open_runs: Iterable[Mapping[str, Any]], here: RunOwner, probe: ProcessProbe
                ) -> list[tuple[int, str, RunOwner, str]]:
    """Of the open runs (rows with run_id, serial, owner), those whose owner process is
    provably gone, seen from ``here``: (run_id, serial, owner, why). Open runs without an
    owner (begun before migration 0002) are left alone: nothing proves their station
    stopped."""
    gone = []
    for row in open_runs:
        owner = RunOwner.from_json(row["owner"])
        if owner is None:
            continue
        why = why_gone(owner, here, probe)
        if why is not None:
            gone.append((int(row["run_id"]), str(row["serial"]), owner, why))
    return gone
