"""``station characterize SERIAL`` and ``station diagnose RECORDING``: the CLI.md contract.

One characterization of a simulated unit (about 20 s on the bench) serves
every test here: its recording is then diagnosed again through ``diagnose``.
"""

from __future__ import annotations

import contextlib
import json
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

from station.benches import SIM_SPEC, open_bench
from station.cli import main
from station.core import NOMINAL_TRIMS, Trims
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

# Characterizations and diagnoses through the command line: about a minute.
pytestmark = pytest.mark.slow

SERIAL = "SN4242"
TRIMS = Trims(30.0, -20.0, 10100.0, 9900.0)


@dataclass(frozen=True)
class Characterized:
    doc: dict[str, Any]
    exit_code: int
    home: Path
    trims_after: Trims


def _run(args: list[str]) -> int:
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(sys, "argv", ["station", *args])
        with pytest.raises(SystemExit) as stop:
            main()
    return int(stop.value.code or 0)


def _run_json(args: list[str], sink: Path) -> tuple[int, dict[str, Any]]:
    """The command's exit code and its ``--json`` document, stdout written to ``sink``:
    a module fixture has no capsys."""
    with sink.open("w", encoding="utf-8") as out, contextlib.redirect_stdout(out):
        code = _run(args)
    return code, json.loads(sink.read_text(encoding="utf-8"))


def _drive_trims(serial: str) -> Trims:
    with open_bench(SIM_SPEC, parse_serial(serial)) as session:
        return session.drive.read_trims()


@pytest.fixture(scope="module")
def characterized(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Characterized]:
    home = tmp_path_factory.mktemp("characterize")
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATION_HOME", str(home))
        patch.delenv("STATION_DB", raising=False)
        patch.delenv("STATION_BENCH", raising=False)
        # A unit calibrated before: characterization must run around its own trims.
        with open_bench(SIM_SPEC, parse_serial(SERIAL)) as session:
            session.drive.write_trims(TRIMS)
            session.drive.store()
        code, doc = _run_json(["characterize", SERIAL, "--json"], home / "out.json")
        yield Characterized(doc, code, home, _drive_trims(SERIAL))


def test_characterize_gives_the_diagnosis_keys_and_its_recording(
    characterized: Characterized,
) -> None:
    doc = characterized.doc
    assert characterized.exit_code == 0
    assert {"mismatch", "located", "effects", "fit", "recording"} <= doc.keys()
    assert {"before", "after"} <= doc["fit"].keys()
    recording = Path(doc["recording"])
    assert recording.is_file() and recording.suffix == ".blf"
    assert recording.parent == characterized.home / "recordings" / SERIAL
    assert Path(doc["report"]).is_file()
    assert len(doc["conditions"]) >= 12  # 3 speeds × 3 currents × 2 directions, most of them


def test_characterize_leaves_the_unit_with_the_trims_it_came_with(
    characterized: Characterized,
) -> None:
    assert characterized.trims_after == TRIMS


def test_characterize_runs_its_trim_steps_around_the_units_own_trims(
    characterized: Characterized,
) -> None:
    from station.analysis.reader import read_recording  # noqa: PLC0415

    timeline = read_recording(Path(characterized.doc["recording"]))
    offsets_a = set(timeline.trims[timeline.trims_valid, 0].tolist())
    assert offsets_a == {30, 70}


@dataclass(frozen=True)
class Rediagnosed:
    """The characterization's recording diagnosed twice more through ``diagnose``: in one
    process with a report to a file of its own, and in two worker processes without one."""

    one_process: dict[str, Any]
    two_processes: dict[str, Any]
    report: Path
    beside_before: set[Path]
    beside_after: set[Path]


@pytest.fixture(scope="module")
def rediagnosed(
    characterized: Characterized, tmp_path_factory: pytest.TempPathFactory,
) -> Rediagnosed:
    recording = Path(characterized.doc["recording"])
    folder = tmp_path_factory.mktemp("rediagnosed")
    report = folder / "report.html"
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATION_HOME", str(characterized.home))
        patch.setenv("STATION_DIAGNOSIS_WORKERS", "1")
        code, one = _run_json(["diagnose", str(recording), "--json", "--report", str(report)],
                              folder / "one.json")
        assert code == 0
        before = set(recording.parent.iterdir())
        patch.setenv("STATION_DIAGNOSIS_WORKERS", "2")
        code, two = _run_json(["diagnose", str(recording), "--json", "--no-report"],
                              folder / "two.json")
        assert code == 0
    return Rediagnosed(one, two, report, before, set(recording.parent.iterdir()))


def test_diagnose_reads_the_recording_again_to_the_same_findings(
    characterized: Characterized, rediagnosed: Rediagnosed,
) -> None:
    doc = rediagnosed.one_process
    assert doc["effects"] == characterized.doc["effects"]
    assert doc["fit"]["before"] == pytest.approx(characterized.doc["fit"]["before"])
    assert doc["report"] == str(rediagnosed.report)
    assert rediagnosed.report.is_file()


def test_diagnose_without_report_writes_nothing_beside_the_recording(
    rediagnosed: Rediagnosed,
) -> None:
    assert rediagnosed.two_processes["report"] is None
    assert rediagnosed.beside_after == rediagnosed.beside_before


def test_diagnose_fitting_in_worker_processes_gives_exactly_the_one_process_diagnosis(
    rediagnosed: Rediagnosed,
) -> None:
    one, two = ({k: v for k, v in doc.items() if k != "report"}
                for doc in (rediagnosed.one_process, rediagnosed.two_processes))
    assert one == two
    assert one["fit"]["after_chi2"] > 0


def test_a_number_of_diagnosis_workers_that_is_no_number_is_an_input_error(
    characterized: Characterized, capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    monkeypatch.setenv("STATION_DIAGNOSIS_WORKERS", "two")
    assert _run(["diagnose", characterized.doc["recording"], "--json", "--no-report"]) == 2
    assert "STATION_DIAGNOSIS_WORKERS='two'" in capsys.readouterr().err


def test_diagnose_of_a_missing_recording_is_an_input_error(tmp_path: Path) -> None:
    assert _run(["diagnose", str(tmp_path / "absent.blf"), "--json"]) == 2


def test_diagnose_of_a_run_that_is_not_a_characterization_says_which_schedule_is_needed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    """One speed, one current, one direction: nothing to hold out, nothing to compare.
    Exit 2, the message names the schedules that would do, and nothing is written."""
    v = velocity_for(20.0, 256)
    schedule = Schedule(
        "one-condition",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 100),
            Hold(Phase.CONDITION, v, 1000, NOMINAL_TRIMS, 800),
            Hold(Phase.STEP_OFFSET_A, v, 1000, Trims(40.0, 0.0, 10000.0, 10000.0), 500),
            Hold(Phase.STOP, 0, 1000, NOMINAL_TRIMS, 50),
        ),
        sensor_range_g=8,
    )
    out = tmp_path / "rec" / "one.blf"
    out.parent.mkdir()
    record_schedule(
        SimRecordRequest(out=out, serial=parse_serial("SN4243"),
                         schedule=ScheduleName.CHARACTERIZATION, effects=frozenset(),
                         truth=tmp_path / "truth.json"),
        schedule,
    )
    before = set(out.parent.iterdir())
    assert _run(["diagnose", str(out), "--json"]) == 2
    captured = capsys.readouterr()
    assert "not a characterization" in captured.err
    assert "station characterize" in captured.err
    assert "--schedule characterization" in captured.err
    assert captured.out == ""
    assert set(out.parent.iterdir()) == before
