"""Bad input is refused with exit code 2 before anything happens: the whole matrix.

CLI.md promises that exit code 2 means nothing was done: no bus traffic (here:
no simulated bench ever constructed), nothing recorded (no database file
created), and a message on stderr that names what was wrong. This file runs
every command that takes a serial, a recipe, a database path or a recording
against the malformed ones an operator, a script or an attacker could give.
The parsers' own unit tests (test_serials.py, test_recipes.py,
test_cli_analyze.py) go deeper into each rule; here each kind of bad input
meets each command, through the real command line.
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from station.cli import main
from station.core import NOMINAL_TRIMS, LoadKind
from station.recipes import load_recipe
from station.recording import metadata_path_for
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim import bench as simulator
from station.sim.bench import SimBench
from station.sim.record import SimRecordRequest, record_schedule
from station.store import Store
from tests.cli import Outcome, run_cli

DEFAULT_RECIPE = Path(__file__).parents[1] / "recipes" / "default.toml"


def _run(args: list[str], monkeypatch: pytest.MonkeyPatch,
         capsys: pytest.CaptureFixture[str]) -> Outcome:
    """The CLI in-process, as ``tests/test_calibrate.py`` runs it."""
    return run_cli(args, monkeypatch, capsys)


class BenchConstructed(AssertionError):
    """A command went on to the bench although its input was bad."""


@pytest.fixture
def benches_built(monkeypatch: pytest.MonkeyPatch) -> list[str]:
    """Counts simulated benches constructed; constructing one fails the command at once."""
    built: list[str] = []

    class NoBench(SimBench):
        def __init__(self, *args: Any, **kwargs: Any) -> None:
            built.append("SimBench")
            raise BenchConstructed("a simulated bench was constructed for bad input")

    monkeypatch.setattr(simulator, "SimBench", NoBench)
    return built


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "results" / "station.db"


def _refused(outcome: Outcome, db: Path, station_home: Path, built: list[str]) -> None:
    """Exit 2, nothing on stdout, an error on stderr, no database and no bench."""
    assert outcome.code == 2, outcome.stderr
    assert outcome.stdout == ""
    assert "error" in outcome.stderr.lower()
    assert not db.exists()
    assert not (station_home / "station.db").exists()
    assert built == []


# -- serials ------------------------------------------------------------------------------

BAD_SERIALS = [
    "../x", "SN1/../../x", "SN1/x", "..", "/etc/passwd", "SN-1", "", " ", "SN01", "SN0123",
    "SN99999999999", "SN4294967296", "sn123", "SN", "123", "SN12a", "SN1 ", " SN1", "SN1\n",
    "SN 1", "SN1;rm -rf ~", "SN１２３", "SN1.5", "SN+1", "SN0x10",
]

SERIAL_COMMANDS = {
    "calibrate": ["calibrate", "{}"],
    "recalibrate": ["recalibrate", "{}", "--reason", "field return", "--force"],
    "verify": ["verify", "{}"],
    "history": ["history", "{}"],
    "characterize": ["characterize", "{}", "--no-report"],
    "query": ["query", "--serial", "{}"],
    "sim-unit": ["sim", "unit", "{}"],
}


def _with(template: list[str], value: str, db: Path) -> list[str]:
    args = [value if part == "{}" else part for part in template]
    return args if template[0] == "sim" else [*args, "--db", str(db)]


@pytest.mark.parametrize("command", list(SERIAL_COMMANDS))
@pytest.mark.parametrize("serial", BAD_SERIALS, ids=repr)
def test_a_malformed_serial_is_refused_before_the_database_and_the_bench(
    command: str, serial: str, db: Path, station_home: Path, benches_built: list[str],
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    outcome = _run(_with(SERIAL_COMMANDS[command], serial, db), monkeypatch, capsys)
    _refused(outcome, db, station_home, benches_built)
    assert "serial" in outcome.stderr
    # Nothing named after the serial anywhere: path tricks went nowhere.
    assert not (db.parent / "recordings").exists()
    assert not (station_home / "sim").exists()


def test_a_serial_with_non_ascii_digits_is_refused(
    db: Path, station_home: Path, benches_built: list[str],
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    outcome = _run(["history", "SN1\u0662", "--db", str(db)], monkeypatch, capsys)
    _refused(outcome, db, station_home, benches_built)


# -- recipes ------------------------------------------------------------------------------


def _variant(folder: Path, name: str, *edits: tuple[str, str]) -> Path:
    """The default recipe as ``name.toml`` with each ``old`` text replaced by ``new``."""
    text = DEFAULT_RECIPE.read_text(encoding="utf-8").replace(
        'name = "default"', f'name = "{name}"')
    for old, new in edits:
        assert old in text, old
        text = text.replace(old, new, 1)
    path = folder / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    return path


@dataclass(frozen=True)
class BadRecipe:
    """A recipe argument, made in a folder, and what the refusal must name."""

    make: Any  # (folder) -> the --recipe argument
    names: tuple[str, ...]


BAD_RECIPES = {
    "unknown-key": BadRecipe(
        lambda f: str(_variant(f, "extra", ("[motion]\n", "[motion]\ncolour = \"red\"\n"))),
        ("motion.colour",)),
    "unknown-table": BadRecipe(
        lambda f: str(_variant(f, "table", ("[motion]\n", "[motor]\nx = 1\n\n[motion]\n"))),
        ("motor",)),
    "wrong-type": BadRecipe(
        lambda f: str(_variant(f, "typed", ("sensor_range_g = 16", 'sensor_range_g = "16"'))),
        ("motion.sensor_range_g",)),
    "bool-for-number": BadRecipe(
        lambda f: str(_variant(f, "boolean", ("dwell_periods = 4", "dwell_periods = true"))),
        ("motion.dwell_periods",)),
    "out-of-range": BadRecipe(
        lambda f: str(_variant(f, "ranged", ("sensor_range_g = 16", "sensor_range_g = 3"))),
        ("motion.sensor_range_g",)),
    "not-finite": BadRecipe(
        lambda f: str(_variant(f, "infinite", ("electrical_hz = 20.0", "electrical_hz = inf"))),
        ("motion.electrical_hz",)),
    "cross-field": BadRecipe(
        lambda f: str(_variant(f, "crossed", ("amplitude_mA = 1000", "amplitude_mA = 1001"))),
        ("motion.amplitude_mA", "product.rated_current_mA")),
    "missing-key": BadRecipe(
        lambda f: str(_variant(f, "missing", ("rotor_teeth = 50\n", ""))),
        ("product.rotor_teeth",)),
    "toml-syntax": BadRecipe(
        lambda f: str(_variant(f, "syntax", ("amplitude_mA = 1000", "amplitude_mA = = 1000"))),
        ("syntax.toml", "line")),
    "name-not-stem": BadRecipe(
        lambda f: str(_variant(f, "renamed", ('name = "renamed"', 'name = "default"'))),
        ("renamed.toml", "name")),
    "not-utf8": BadRecipe(
        lambda f: _write(f / "latin.toml", b'name = "latin"\ndescription = "\xe9"\n'),
        ("latin.toml",)),
    "empty-file": BadRecipe(lambda f: _write(f / "empty.toml", b""), ("empty.toml",)),
    "path-trick": BadRecipe(lambda f: "../../etc/passwd", ("../../etc/passwd",)),
    "parent-name": BadRecipe(lambda f: "..", ("no such recipe",)),
    "unknown-name": BadRecipe(lambda f: "nosuch", ("nosuch", "no such recipe")),
    "missing-file": BadRecipe(lambda f: str(f / "nowhere" / "gone.toml"), ("gone.toml",)),
    "a-directory": BadRecipe(lambda f: _folder(f / "folder.toml"), ("folder.toml",)),
}

RECIPE_COMMANDS = {
    "calibrate": ["calibrate", "SN123", "--recipe", "{}"],
    "recalibrate": ["recalibrate", "SN123", "--reason", "field return", "--force",
                    "--recipe", "{}"],
    "characterize": ["characterize", "SN123", "--no-report", "--recipe", "{}"],
}


def _write(path: Path, data: bytes) -> str:
    path.write_bytes(data)
    return str(path)


def _folder(path: Path) -> str:
    path.mkdir()
    return str(path)


@pytest.mark.parametrize("command", list(RECIPE_COMMANDS))
@pytest.mark.parametrize("case", list(BAD_RECIPES))
def test_a_bad_recipe_is_refused_naming_the_field_before_the_database_and_the_bench(
    command: str, case: str, tmp_path: Path, db: Path, station_home: Path,
    benches_built: list[str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    bad = BAD_RECIPES[case]
    recipe = bad.make(tmp_path)
    outcome = _run(_with(RECIPE_COMMANDS[command], recipe, db), monkeypatch, capsys)
    assert outcome.code == 2, outcome.stderr
    assert outcome.stdout == ""
    for name in bad.names:
        assert name in outcome.stderr
    assert benches_built == []
    assert not (station_home / "station.db").exists()
    assert not db.exists()


def test_recalibrate_with_a_bad_recipe_creates_no_database(
    tmp_path: Path, db: Path, benches_built: list[str],
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    outcome = _run(["recalibrate", "SN123", "--reason", "r", "--force", "--recipe", "nosuch",
                    "--db", str(db)], monkeypatch, capsys)
    assert outcome.code == 2
    assert not db.exists()


INJECTIONS = [
    "__import__('os').system('touch {marker}')",
    "$(touch {marker})",
    "`touch {marker}`",
    "{{{{7*7}}}}; open('{marker}', 'w')",
    "'; import os; os.system('touch {marker}'); '",
]


@pytest.mark.parametrize("payload", INJECTIONS)
def test_code_in_recipe_values_is_refused_or_kept_as_inert_text(
    payload: str, tmp_path: Path, db: Path, station_home: Path, benches_built: list[str],
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    marker = tmp_path / "pwned"
    text = json.dumps(payload.format(marker=marker))  # a TOML basic string
    # Where a number or a word from a list is expected: refused, naming the field.
    for field, old in (("motion.amplitude_mA", "amplitude_mA = 1000"),
                       ("method", 'method = "coherent"'),
                       ("product.microsteps", "microsteps = 256")):
        key = old.split(" = ")[0]
        recipe = _variant(tmp_path, "injected", (old, f"{key} = {text}"))
        outcome = _run(["calibrate", "SN123", "--recipe", str(recipe), "--db", str(db)],
                       monkeypatch, capsys)
        _refused(outcome, db, station_home, benches_built)
        assert field in outcome.stderr
    # Where text is expected, it stays text: read verbatim through the real command, which
    # then stops at an unusable database path, before any bench.
    recipe = _variant(tmp_path, "described", ('description = "', f"description = {text}\n#"))
    assert load_recipe(recipe).description == payload.format(marker=marker)
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where the database folder should be")
    outcome = _run(["calibrate", "SN123", "--recipe", str(recipe),
                    "--db", str(blocker / "station.db")], monkeypatch, capsys)
    assert outcome.code == 2 and str(blocker) in outcome.stderr
    assert benches_built == []
    assert not marker.exists()


# -- database paths -----------------------------------------------------------------------

DB_COMMANDS = {
    "calibrate": ["calibrate", "SN123"],
    "recalibrate": ["recalibrate", "SN123", "--reason", "field return", "--force"],
    "verify": ["verify", "SN123"],
    "history": ["history", "SN123"],
    "query": ["query"],
    "stats": ["stats"],
}


def _blocked(tmp_path: Path) -> Path:
    """A database path whose folder is a file."""
    blocker = tmp_path / "results"
    blocker.write_text("a file where the database folder should be")
    return blocker / "station.db"


def _deeply_blocked(tmp_path: Path) -> Path:
    return _blocked(tmp_path).parent / "deeper" / "station.db"


def _directory(tmp_path: Path) -> Path:
    folder = tmp_path / "station.db"
    folder.mkdir()
    return folder


BAD_DB_PATHS = {"folder-is-a-file": _blocked, "ancestor-is-a-file": _deeply_blocked,
                "a-directory": _directory}


@pytest.mark.parametrize("via_env", [False, True], ids=["--db", "STATION_DB"])
@pytest.mark.parametrize("command", list(DB_COMMANDS))
@pytest.mark.parametrize("kind", list(BAD_DB_PATHS))
def test_a_path_that_cannot_hold_the_database_is_refused_naming_it(
    kind: str, command: str, via_env: bool, tmp_path: Path, station_home: Path,
    benches_built: list[str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = BAD_DB_PATHS[kind](tmp_path)
    before = sorted(p.name for p in tmp_path.rglob("*"))
    args = list(DB_COMMANDS[command])
    if via_env:
        monkeypatch.setenv("STATION_DB", str(path))
    else:
        args += ["--db", str(path)]
    outcome = _run(args, monkeypatch, capsys)
    assert outcome.code == 2, outcome.stderr
    assert outcome.stdout == ""
    assert f"database {path}: cannot hold the results database" in outcome.stderr
    assert benches_built == []
    assert sorted(p.name for p in tmp_path.rglob("*")) == before  # nothing created anywhere
    assert not (station_home / "station.db").exists()


def test_characterize_refuses_a_database_folder_that_is_a_file(
    tmp_path: Path, benches_built: list[str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # characterize records no run: its recording goes beside the database, and cannot.
    path = _blocked(tmp_path)
    outcome = _run(["characterize", "SN123", "--no-report", "--db", str(path)],
                   monkeypatch, capsys)
    assert outcome.code == 2, outcome.stderr
    assert str(path.parent) in outcome.stderr
    assert benches_built == []


_CLI_WITHOUT_BENCH = textwrap.dedent("""
    # The real CLI, several times in one process, with the simulated bench forbidden.
    import contextlib, io, json, sys
    import station.sim.bench as simulator
    from station.cli import main

    built = []

    class NoBench(simulator.SimBench):
        def __init__(self, *args, **kwargs):
            built.append(1)
            raise AssertionError("a simulated bench was constructed for bad input")

    simulator.SimBench = NoBench  # the module station.benches loads by name
    results = []
    for argv in json.loads(sys.argv[1]):
        sys.argv = ["station", *argv]
        out, err = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                main()
                code = 0
            except SystemExit as exc:
                code = exc.code if isinstance(exc.code, int) else 1
        results.append({"code": code, "stdout": out.getvalue(),
                        "stderr": " ".join(err.getvalue().split()), "benches": len(built)})
    print(json.dumps(results))
""")


def _unprivileged_prefix() -> list[str]:
    """How to run a process that permission bits apply to.

    Root writes through read-only modes; root without its capabilities
    (``setpriv``) does not, so the test still runs as root, in CI containers.
    """
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    if setpriv is None:
        pytest.skip("running as root, whom permissions do not stop, and setpriv is missing")
    return [setpriv, "--bounding-set", "-all", "--inh-caps", "-all"]


def test_a_read_only_folder_or_file_is_refused_naming_it(
    tmp_path: Path, station_home: Path,
) -> None:
    prefix = _unprivileged_prefix()
    sealed = tmp_path / "sealed"  # read-only folder, empty
    sealed.mkdir()
    kept = tmp_path / "kept"  # read-only folder holding a database
    kept.mkdir()
    Store(kept / "station.db").close()
    frozen = tmp_path / "frozen" / "station.db"  # read-only database file
    Store(frozen).close()
    sealed.chmod(0o555)
    kept.chmod(0o555)
    frozen.chmod(0o444)
    cases = [(sealed / "station.db", "is not writable"), (kept / "station.db", "is not writable"),
             (frozen, "not readable and writable")]
    argvs = [[*args, "--db", str(path)] for path, _ in cases
             for args in (DB_COMMANDS["calibrate"], DB_COMMANDS["verify"],
                          DB_COMMANDS["history"])]
    try:
        done = subprocess.run([*prefix, sys.executable, "-c", _CLI_WITHOUT_BENCH,
                               json.dumps(argvs)], capture_output=True, text=True,
                              timeout=120, check=False)
    finally:
        sealed.chmod(0o755)
        kept.chmod(0o755)
    assert done.returncode == 0, done.stderr
    results = json.loads(done.stdout)
    expected = [(path, message) for path, message in cases for _ in range(3)]
    for argv, result, (path, message) in zip(argvs, results, expected, strict=True):
        assert result["code"] == 2, (argv, result["stderr"])
        assert f"database {path}: cannot hold the results database" in result["stderr"]
        assert message in result["stderr"]
        assert result["stdout"] == ""
    assert results[-1]["benches"] == 0
    assert not (sealed / "station.db").exists()
    assert not (station_home / "station.db").exists()


def test_a_file_that_is_not_a_database_stops_the_station_and_is_left_alone(
    tmp_path: Path, benches_built: list[str], monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # Not the operator's typo but the station's data in trouble: exit 3, for a technician.
    path = tmp_path / "station.db"
    garbage = b"this was the results database until the disk said otherwise" * 64
    path.write_bytes(garbage)
    for args in (DB_COMMANDS["calibrate"], DB_COMMANDS["history"]):
        outcome = _run([*args, "--db", str(path)], monkeypatch, capsys)
        assert outcome.code == 3, outcome.stderr
        assert f"database {path}" in outcome.stderr and "not a database" in outcome.stderr
    assert benches_built == []
    assert path.read_bytes() == garbage


# -- recordings ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """A small, valid recording and its metadata, to spoil."""
    root = tmp_path_factory.mktemp("recording")
    schedule = Schedule(
        "tiny",
        (Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 50),
         Hold(Phase.BASELINE, velocity_for(20.0, 256), 1000, NOMINAL_TRIMS, 200),
         Hold(Phase.STOP, 0, 1000, NOMINAL_TRIMS, 20)),
        sensor_range_g=8,
    )
    (root / "rec").mkdir()
    request = SimRecordRequest(
        out=root / "rec" / "run.blf", serial=parse_serial("SN123"),
        schedule=ScheduleName.CALIBRATION, effects=frozenset(), seed=1, load=LoadKind.DISK,
        loss=0.0, truth=root / "truth.json",
    )
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATION_HOME", str(root / "home"))
        yield record_schedule(request, schedule).recording


def _spoiled(folder: Path, original: Path, suffix: str = ".blf", *, data: bytes | None = None,
             metadata: bytes | None = None, keep_metadata: bool = True) -> Path:
    log = folder / f"run{suffix}"
    log.write_bytes(original.read_bytes() if data is None else data)
    if metadata is not None:
        metadata_path_for(log).write_bytes(metadata)
    elif keep_metadata:
        shutil.copyfile(metadata_path_for(original), metadata_path_for(log))
    return log


def _half(path: Path) -> bytes:
    data = path.read_bytes()
    return data[: len(data) // 2]


BAD_RECORDINGS: dict[str, tuple[Any, str]] = {
    "empty": (lambda f, r: _spoiled(f, r, data=b""), "cannot be read as BLF"),
    "truncated": (lambda f, r: _spoiled(f, r, data=_half(r)), "truncated"),
    "garbage-blf": (lambda f, r: _spoiled(f, r, data=bytes(range(256)) * 20),
                    "cannot be read as BLF"),
    # A BLF signature and a header cut short: what the reader unpacks is not there.
    "short-blf-header": (lambda f, r: _spoiled(f, r, data=b"LOGG\x90\x00\x00\x00garbage"),
                         "cannot be read as BLF (truncated or not that format): its header "
                         "is cut short"),
    "garbage-mf4": (lambda f, r: _spoiled(f, r, ".mf4", data=b"\x00\xff" * 2000),
                    "cannot be read as MF4"),
    "garbage-asc": (lambda f, r: _spoiled(f, r, ".asc", data=b"\x00garbage\n" * 50),
                    "truncated: an ASC log is text ending with 'End TriggerBlock'; this one is "
                    "not text"),
    "garbage-csv": (lambda f, r: _spoiled(f, r, ".csv", data=b"a,b,c\n1,2\n"),
                    "cannot be parsed"),
    "garbage-log": (lambda f, r: _spoiled(f, r, ".log", data=b"(1.0) can0 zzz#\n"),
                    "cannot be parsed"),
    "wrong-suffix": (lambda f, r: _spoiled(f, r, ".txt"), "unknown recording suffix '.txt'"),
    "no-suffix": (lambda f, r: _spoiled(f, r, ""), "unknown recording suffix"),
    "missing-metadata": (lambda f, r: _spoiled(f, r, keep_metadata=False),
                         "metadata file run.json is missing"),
    "metadata-not-json": (lambda f, r: _spoiled(f, r, metadata=b'{"format": '),
                          "metadata is not valid JSON"),
    "metadata-not-an-object": (lambda f, r: _spoiled(f, r, metadata=b"[1, 2]"),
                               "metadata must be a JSON object"),
    "metadata-empty-object": (lambda f, r: _spoiled(f, r, metadata=b"{}"), "missing key"),
    "missing-file": (lambda f, r: f / "nowhere.blf", "nowhere.blf: no such recording"),
    "a-directory": (lambda f, r: Path(_folder(f / "folder.blf")), "folder.blf"),
}


@pytest.mark.parametrize("command", ["analyze", "diagnose"])
@pytest.mark.parametrize("case", list(BAD_RECORDINGS))
def test_a_malformed_recording_is_refused_with_a_message(
    command: str, case: str, recording: Path, tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    make, message = BAD_RECORDINGS[case]
    folder = tmp_path / "spoiled"
    folder.mkdir()
    path = make(folder, recording)
    before = sorted(folder.rglob("*"))
    args = [command, str(path), "--json"] + (["--no-report"] if command == "diagnose" else [])
    outcome = _run(args, monkeypatch, capsys)
    assert outcome.code == 2, outcome.stderr
    assert outcome.stdout == ""
    assert message in " ".join(outcome.stderr.split())
    assert "unpack" not in outcome.stderr and "Traceback" not in outcome.stderr
    assert sorted(folder.rglob("*")) == before  # no report, no partial output


@pytest.mark.parametrize("command", ["analyze", "diagnose"])
def test_metadata_that_is_not_text_is_refused_with_a_message(
    command: str, recording: Path, tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    path = _spoiled(tmp_path, recording, metadata=b"\xff\xfe\x00garbage")
    monkeypatch.setattr(sys, "argv", ["station", command, str(path), "--json"])
    try:
        main()
    except SystemExit as stop:
        assert stop.code == 2
    except UnicodeDecodeError:
        pytest.fail("UnicodeDecodeError escaped the CLI")
    assert "metadata" in capsys.readouterr().err
