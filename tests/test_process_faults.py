"""The station survives what happens to its process: signals, kill -9, neighbours.

A line controller stops a station with SIGTERM, an operator with Ctrl-C, a
power cut or the OOM killer with no warning at all; QA reads the database
while stations write it, and several stations write one file. Each must leave
the database whole and every run accounted for, so each is played here on the
real command line in real processes (simulated bench, temporary homes).
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import sqlite3
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import pytest

from station import records
from station import store as store_module
from station.cli import main
from station.runs import Verdict
from station.signals import Stopped, held, stop_on_signals, stop_reason
from station.sim import record as sim_record
from station.store import Store

STEP_TIMEOUT_S = 60.0
SWEEPING = "s  sweep round "
"""What the operator's step line shows once the sweeps run ("step 4 of 9  0.6 s  sweep round
1/3: …")."""
"""Generous for a loaded 2-core CI machine; a healthy run takes about 10 s."""

LOCKED = "database is locked"


# -- the signal handling itself, in this process ---------------------------------------


def _deliver(signum: int) -> None:
    """Send ``signum`` to this process and give its Python handler the chance to run."""
    os.kill(os.getpid(), signum)
    for _ in range(100):  # the handler runs between bytecodes: a loop gives it them
        time.sleep(0.001)


@pytest.mark.parametrize(
    ("signum", "reason"),
    [(signal.SIGINT, "aborted by the operator (SIGINT)"), (signal.SIGTERM, "stopped by SIGTERM")],
)
def test_a_first_signal_raises_stopped_naming_it_and_the_old_handlers_come_back(
    signum: signal.Signals, reason: str
) -> None:
    before = {sig: signal.getsignal(sig) for sig in (signal.SIGINT, signal.SIGTERM)}
    with pytest.raises(Stopped) as stopped, stop_on_signals() as state:
        assert signal.getsignal(signum) is not before[signum]
        _deliver(signum)
    assert isinstance(stopped.value, KeyboardInterrupt)
    assert str(stopped.value) == reason == stop_reason(signum)
    assert stopped.value.signum == signum
    assert state.stopping and state.reason == reason
    assert {sig: signal.getsignal(sig) for sig in before} == before


def test_signals_while_stopping_are_logged_and_ignored_so_cleanup_finishes(
    caplog: pytest.LogCaptureFixture,
) -> None:
    cleaned_up = False
    with stop_on_signals(), caplog.at_level(logging.WARNING, logger="station.signals"):
        try:
            _deliver(signal.SIGINT)
            pytest.fail("the first signal must stop the station")
        except Stopped:
            # Disabling the drive, recording the run: an impatient operator presses again.
            _deliver(signal.SIGINT)
            _deliver(signal.SIGTERM)
            cleaned_up = True
    assert cleaned_up
    ignored = [r.getMessage() for r in caplog.records if "ignored" in r.getMessage()]
    assert len(ignored) == 2
    assert ignored[0].startswith("SIGINT") and ignored[1].startswith("SIGTERM")


def test_a_stop_during_a_database_write_is_raised_once_the_write_is_done() -> None:
    steps: list[str] = []
    with pytest.raises(Stopped, match="SIGTERM"), stop_on_signals():
        with held():
            with held():  # nested: only the outermost section delivers
                _deliver(signal.SIGTERM)
                steps.append("inner write done")
            steps.append("outer write done")
        steps.append("went on after the write")  # never: the stop comes first
    assert steps == ["inner write done", "outer write done"]


def test_outside_stop_on_signals_a_held_section_changes_nothing() -> None:
    # Compared with what the process had, not with Python's default: a test run started in
    # the background by a shell without job control inherits SIGINT ignored.
    before = signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)
    delivered: list[str] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: delivered.append("now"))
    try:
        with held():
            assert signal.getsignal(signal.SIGINT) == before[0]
            # The process's own handler runs inside the section, not deferred past it.
            _deliver(signal.SIGTERM)
            assert delivered == ["now"]
            delivered.append("section went on")
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert delivered == ["now", "section went on"]
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before
    assert (signal.getsignal(signal.SIGINT), signal.getsignal(signal.SIGTERM)) == before


def _main(args: list[str], monkeypatch: pytest.MonkeyPatch,
          capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    monkeypatch.setattr(sys, "argv", ["station", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    code = stop.value.code
    return code if isinstance(code, int) else -1, " ".join(capsys.readouterr().err.split())


def test_a_stop_outside_any_run_exits_3_naming_the_signal(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    # sim record records no run: the stop itself is what the CLI reports.
    def record(*args: object, **kwargs: object) -> None:
        _deliver(signal.SIGTERM)
        pytest.fail("the signal must stop the recording")

    # The command imports the simulator when it runs: patched where it is imported from.
    monkeypatch.setattr(sim_record, "record_simulation", record)
    before = signal.getsignal(signal.SIGTERM)
    code, err = _main(["sim", "record", str(tmp_path / "out.blf"), "--serial", "SN123",
                       "--schedule", "calibration"], monkeypatch, capsys)
    assert code == 3
    assert "aborted: stopped by SIGTERM" in err
    assert signal.getsignal(signal.SIGTERM) is before


def test_ctrl_c_in_a_short_command_exits_3_not_typer_s_130(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    def interrupted(*args: object) -> None:
        raise KeyboardInterrupt

    monkeypatch.setattr(records, "query", interrupted)
    code, err = _main(["query", "--db", str(tmp_path / "station.db")], monkeypatch, capsys)
    assert code == 3
    assert "aborted" in err


# -- the real command line, in other processes -------------------------------------------


@dataclass
class Station:
    """A station process whose output goes to files (no reader threads to leak)."""

    process: subprocess.Popen[bytes]
    stdout: Path
    stderr: Path

    def err(self) -> str:
        return self.stderr.read_text(encoding="utf-8", errors="replace")

    def wait(self, timeout: float = STEP_TIMEOUT_S) -> int:
        try:
            return self.process.wait(timeout)
        except subprocess.TimeoutExpired:
            self.process.kill()
            self.process.wait()
            pytest.fail(f"the station did not end within {timeout} s:\n{self.err()}")

    def wait_for(self, predicate_text: str, timeout: float = STEP_TIMEOUT_S, *,
                 anywhere: bool = False) -> None:
        """Until a line of stderr starts with (or holds) ``predicate_text``; fail if it ends."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            lines = self.err().splitlines()
            if any(line.startswith(predicate_text) or (anywhere and predicate_text in line)
                   for line in lines):
                return
            if self.process.poll() is not None:
                pytest.fail(f"the station ended before {predicate_text!r}:\n{self.err()}")
            time.sleep(0.02)
        self.process.kill()
        self.process.wait()
        pytest.fail(f"no {predicate_text!r} within {timeout} s:\n{self.err()}")


@pytest.fixture
def env(station_home: Path) -> dict[str, str]:
    """The environment of the station processes: this test's home, nothing inherited."""
    environment = {k: v for k, v in os.environ.items()
                   if k not in ("STATION_DB", "STATION_BENCH", "STATION_OPERATOR")}
    environment.update(STATION_HOME=str(station_home), PYTHONUNBUFFERED="1",
                       OPENBLAS_NUM_THREADS="1", COLUMNS="200")
    return environment


@pytest.fixture
def processes() -> Iterator[list[Station]]:
    """Every station process a test starts is gone when it ends, whatever happened."""
    started: list[Station] = []
    yield started
    for station in started:
        if station.process.poll() is None:
            station.process.kill()
        station.process.wait()


def _start(args: Sequence[str], env: dict[str, str], folder: Path, name: str,
           processes: list[Station], *, module: bool = True) -> Station:
    stdout, stderr = folder / f"{name}.out", folder / f"{name}.err"
    command = [sys.executable, "-m", "station.cli", *args] if module else [sys.executable, *args]
    with stdout.open("wb") as out, stderr.open("wb") as err:
        process = subprocess.Popen(command, stdout=out, stderr=err, env=env)
    station = Station(process, stdout, stderr)
    processes.append(station)
    return station


def _cli(args: Sequence[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "station.cli", *args], env=env,
                          capture_output=True, text=True, timeout=STEP_TIMEOUT_S, check=False)


def _integrity(db: Path) -> str:
    conn = sqlite3.connect(db)
    try:
        return str(conn.execute("PRAGMA integrity_check").fetchone()[0])
    finally:
        conn.close()


@pytest.mark.parametrize(
    ("signals", "reason"),
    [
        ((signal.SIGINT,), "aborted by the operator (SIGINT)"),
        ((signal.SIGTERM,), "stopped by SIGTERM"),
        # An impatient stop: the second and third arrive while the station is stopping.
        ((signal.SIGTERM, signal.SIGINT, signal.SIGTERM), "stopped by SIGTERM"),
    ],
    ids=["sigint", "sigterm", "sigterm-then-more"],
)
def test_a_signal_mid_sweep_ends_the_run_aborted_with_its_recording_and_exit_3(
    tmp_path: Path, env: dict[str, str], processes: list[Station],
    signals: tuple[signal.Signals, ...], reason: str,
) -> None:
    db = tmp_path / "results" / "station.db"
    station = _start(["calibrate", "SN123", "--db", str(db)], env, tmp_path, "calibrate",
                     processes)
    station.wait_for(SWEEPING, anywhere=True)
    first, *more = signals
    station.process.send_signal(first)
    if more:
        # Once it is stopping (signals sent together would be handled in signal-number order).
        station.wait_for(f"{first.name} received: stopping", anywhere=True)
        for signum in more:
            station.process.send_signal(signum)
    assert station.wait() == 3, station.err()
    with Store(db) as store:
        (run,) = store.history("SN123")
    assert run.verdict is Verdict.ABORTED, station.err()
    assert run.reason == reason
    assert run.finished_at is not None
    assert run.recording is not None and Path(run.recording).is_file()
    assert run.trims_stored is False
    if len(signals) > 1:
        assert "while the station is stopping: ignored" in " ".join(station.err().split())
    assert _integrity(db) == "ok"


def test_after_kill_9_the_run_stays_open_and_the_next_start_closes_it(
    tmp_path: Path, env: dict[str, str], processes: list[Station],
) -> None:
    db = tmp_path / "results" / "station.db"
    killed = _start(["calibrate", "SN123", "--db", str(db)], env, tmp_path, "killed", processes)
    killed.wait_for(SWEEPING, anywhere=True)
    killed.process.kill()
    assert killed.wait() == -signal.SIGKILL
    pid = killed.process.pid

    # What the killed station left: a consistent file and an open run it owned.
    assert _integrity(db) == "ok"
    with Store(db) as store:
        (run,) = store.history("SN123")
        assert run.verdict is None and run.finished_at is None
        assert run.run_id is not None
        owner = store.open_run_owner(run.run_id)
    assert owner is not None and owner.pid == pid and owner.host == socket.gethostname()

    # The next station process, another unit: it finds the dead owner and closes the run
    # as it begins its own (which is then stopped: its calibration is not the point here).
    nxt = _start(["calibrate", "SN124", "--db", str(db)], env, tmp_path, "next", processes)
    nxt.wait_for(f"run {run.run_id} of SN123 marked aborted", anywhere=True)
    nxt.process.send_signal(signal.SIGTERM)
    assert nxt.wait() == 3, nxt.err()
    with Store(db) as store:
        (run,) = store.history("SN123")
        (new_run,) = store.history("SN124")
    assert new_run.verdict is Verdict.ABORTED and new_run.reason == "stopped by SIGTERM"
    assert run.verdict is Verdict.ABORTED and run.finished_at is not None
    assert run.reason == (
        f"interrupted: station process {pid} on host {socket.gethostname()} ended without "
        f"finishing the run (the process no longer exists; found at the start of run "
        f"{new_run.run_id})"
    )
    assert _integrity(db) == "ok"


_WRITER = textwrap.dedent("""
    # One station process writing runs as fast as it can: begin, finish, N times
    # (N < 0: until the stop file appears, pausing between runs), then how many it wrote.
    import sys, time
    from datetime import UTC, datetime
    from pathlib import Path
    from station.recipes import load_recipe
    from station.runs import RecipeRef, Run, RunKind, Verdict
    from station.store import Store

    db, serial, count = Path(sys.argv[1]), sys.argv[2], int(sys.argv[3])
    go, stop = Path(sys.argv[4]), Path(sys.argv[5])
    recipe = load_recipe("default")
    while not go.exists():
        time.sleep(0.005)
    written = 0
    with Store(db) as store:
        while written < count if count >= 0 else not stop.exists():
            run = Run(serial=serial, kind=RunKind.CALIBRATE,
                      recipe=RecipeRef(recipe.name, recipe.version, recipe.sha256),
                      station_id=1, operator="load", software_version="test", bench="sim")
            store.begin_run(run, recipe.text)
            run.verdict = Verdict.PASS if written % 2 else Verdict.FAIL
            run.reason = f"run {written} of {serial}"
            run.finished_at = datetime.now(UTC)
            store.finish_run(run)
            written += 1
            if count < 0:
                time.sleep(0.01)
    print(written)
""")


def _writers(tmp_path: Path, db: Path, env: dict[str, str], processes: list[Station],
             serials: Sequence[str], count: int, go: Path, stop: Path) -> list[Station]:
    script = tmp_path / "writer.py"
    script.write_text(_WRITER, encoding="utf-8")
    return [_start([str(script), str(db), serial, str(count), str(go), str(stop)], env,
                   tmp_path, f"writer-{serial}", processes, module=False) for serial in serials]


def test_two_station_processes_writing_one_new_database_lose_no_run(
    tmp_path: Path, env: dict[str, str], processes: list[Station],
) -> None:
    db, go, count = tmp_path / "shared" / "station.db", tmp_path / "go", 200
    writers = _writers(tmp_path, db, env, processes, ("SN1", "SN2"), count, go, tmp_path / "x")
    go.touch()  # both start together, on a file neither has created yet
    for writer in writers:
        assert writer.wait() == 0, writer.err()
        assert LOCKED not in writer.err()
    conn = sqlite3.connect(db)
    try:
        rows = conn.execute("SELECT serial, COUNT(*), COUNT(verdict), COUNT(DISTINCT reason) "
                            "FROM runs GROUP BY serial ORDER BY serial").fetchall()
        total = conn.execute("SELECT COUNT(*), COUNT(DISTINCT run_id) FROM runs").fetchone()
    finally:
        conn.close()
    assert rows == [("SN1", count, count, count), ("SN2", count, count, count)]
    assert total == (2 * count, 2 * count)
    assert _integrity(db) == "ok"


_QA_LOOP = textwrap.dedent("""
    # QA at a dashboard: query, history and stats through the real CLI, again and again.
    import contextlib, io, sys, time
    from pathlib import Path
    from station.cli import main

    db, stop = sys.argv[1], Path(sys.argv[2])
    calls = 0
    while not stop.exists():
        for args in (["query", "--json"], ["history", "SN123", "--json"],
                     ["query", "--verdict", "pass", "--format", "csv"], ["stats", "--json"]):
            sys.argv = ["station", *args, "--db", db]
            with contextlib.redirect_stdout(io.StringIO()):
                try:
                    main()
                except SystemExit as exc:
                    if exc.code not in (0, None):
                        print(f"exit {exc.code} from {args}", file=sys.stderr)
                        sys.exit(1)
            calls += 1
            time.sleep(0.1)  # a dashboard, not a busy loop: leave the stations their CPU
    print(calls)
""")


def _quick_recipe(folder: Path) -> Path:
    text = (Path(__file__).parents[1] / "recipes" / "default.toml").read_text(encoding="utf-8")
    for old, new in (('name = "default"', 'name = "quick"'),
                     ("offset_steps_mA = [100, 30, 10]", "offset_steps_mA = [100]"),
                     ("gain_steps = [1000, 300, 100]", "gain_steps = [1000]"),
                     ("dwell_periods = 4                # 0.2", "dwell_periods = 3 # 0.15")):
        assert old in text, old
        text = text.replace(old, new, 1)
    path = folder / "quick.toml"
    path.write_text(text, encoding="utf-8")
    return path


def test_qa_reads_while_stations_write_never_meet_a_locked_database(
    tmp_path: Path, env: dict[str, str], processes: list[Station],
) -> None:
    db, go, stop = tmp_path / "results" / "station.db", tmp_path / "go", tmp_path / "stop"
    Store(db).close()
    # One sweep round and a short verification: a shorter calibration, the same writes.
    quick = _quick_recipe(tmp_path)
    calibration = _start(["calibrate", "SN123", "--recipe", str(quick), "--db", str(db)], env,
                         tmp_path, "calibrate", processes)
    # Another station writing the same file all along, so that readers meet writes.
    (writer,) = _writers(tmp_path, db, env, processes, ("SN900",), -1, go, stop)
    script = tmp_path / "qa.py"
    script.write_text(_QA_LOOP, encoding="utf-8")
    qa = _start([str(script), str(db), str(stop)], env, tmp_path, "qa", processes, module=False)
    go.touch()
    # And QA's command line in a fresh process, opening the file mid-calibration.
    calibration.wait_for(SWEEPING, anywhere=True)
    result = _cli(["query", "--json", "--db", str(db)], env)
    assert result.returncode == 0, result.stderr
    assert LOCKED not in result.stderr
    assert isinstance(json.loads(result.stdout), list)
    # Its last write, recording the run, meets the others' reads and writes too.
    assert calibration.wait() == 0, calibration.err()
    stop.touch()
    assert writer.wait() == 0, writer.err()
    assert qa.wait() == 0, qa.err()
    for station in (calibration, writer, qa):
        assert LOCKED not in station.err()
    qa_calls = int(qa.stdout.read_text())
    written = int(writer.stdout.read_text())
    assert qa_calls >= 8 and written >= 10  # they did overlap the calibration
    with Store(db) as store:
        (calibrated,) = store.history("SN123")
        assert calibrated.verdict is Verdict.PASS
        assert len(store.history("SN900")) == written
    assert _integrity(db) == "ok"


def test_qa_reads_past_a_writer_that_holds_the_lock(
    tmp_path: Path, env: dict[str, str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    db = tmp_path / "results" / "station.db"
    Store(db).close()
    writer = sqlite3.connect(db, isolation_level=None)
    try:
        # A station between BEGIN and COMMIT, as long as it likes (EXCLUSIVE: even without
        # WAL no reader could get in, so this fails unless the readers have their snapshot).
        writer.execute("BEGIN EXCLUSIVE")
        writer.execute("INSERT INTO recipes VALUES ('x', 'x', '1', 'x', 'x')")
        result = _cli(["query", "--json", "--db", str(db)], env)  # a fresh process
        assert result.returncode == 0, result.stderr
        assert json.loads(result.stdout) == []
        # And this one, with no busy timeout at all: a reader that had to wait for the
        # writer's lock would fail at once with "database is locked", where with the
        # station's 5 s it would only have been slower, which no clock here could tell.
        monkeypatch.setattr(store_module, "BUSY_TIMEOUT_MS", 0)
        for args in (["history", "SN123", "--json"], ["stats", "--json"]):
            code, err = _main([*args, "--db", str(db)], monkeypatch, capsys)
            assert code == 0, err
        writer.execute("ROLLBACK")
    finally:
        writer.close()
