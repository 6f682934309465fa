"""``station calibrate --bench sim-modbus``: a drive reached over Modbus, the sensor on CAN.

No SYNC angle reaches the station from a Modbus drive, so these check that the
magnitude method still lands on the plant's optimum, that the recording can be
analysed again off the bench from the station's write log, that a recipe
needing the angle is refused before anything happens, and that a drive that
falls silent mid-run gives an error run and ends disabled.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import pytest

from drivers.base import DriveState
from station import benches
from station.analysis.commanded import DRIVE_COMMANDS_KEY
from station.analysis.pipeline import AnalysisOptions, analyze
from station.analysis.reader import read_recording
from station.recording import read_metadata
from station.runs import Verdict
from station.serials import parse_serial
from station.service import Station, calibrate
from station.sim import bench as simulator
from station.sim.bench import SimBench
from station.sim.record import describe_unit
from station.steps import Step
from station.store import Store
from tests.test_calibrate import GAIN_TOLERANCE, LAST_STDERR, OFFSET_TOLERANCE_mA, _run


def _close_to_optimum(trims: dict[str, float]) -> None:
    truth = describe_unit(parse_serial("SN123"))["optimal_trims"]
    for key in ("offset_a_mA", "offset_b_mA"):
        assert abs(trims[key] - truth[key]) <= OFFSET_TOLERANCE_mA, key
    for key in ("gain_a", "gain_b"):
        assert abs(trims[key] - truth[key]) <= GAIN_TOLERANCE, key


def test_calibrate_on_the_modbus_bench_lands_on_the_optimum_and_its_recording_reanalyses(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    db = tmp_path / "station.db"
    code, doc = _run(["calibrate", "SN123", "--bench", "sim-modbus", "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 0, doc["reason"]
    assert doc["verdict"] == "pass" and doc["method"] == "paper"
    _close_to_optimum(doc["trims"])
    assert any("without a reset" in w for w in doc["warnings"])
    # The recording holds the sensor's frames and the station's write log for the drive.
    recording = Path(doc["recording"])
    metadata = read_metadata(recording)
    assert metadata.extra["drive_transport"] == "modbus"
    assert metadata.extra[DRIVE_COMMANDS_KEY]
    # The magnitude rounds' holds (2 + 5 periods, one of them lost to each write's
    # uncertain instant) leave too short a stretch for the data to judge their settling:
    # offline, the recipe's settle is given, as `station analyze --settle-periods` does.
    offline = analyze(read_recording(recording), AnalysisOptions(settle_periods=2))
    assert not offline.timeline.drive_reported
    _close_to_optimum(offline.estimate.trims.as_dict())
    # And the unit's EEPROM, read over Modbus in a new session, holds what was recorded.
    code, match = _run(["verify", "SN123", "--bench", "sim-modbus", "--db", str(db), "--json"],
                       monkeypatch, capsys)
    assert code == 0 and match["match"] is True
    assert match["calibration_record"]["count"] == 1


def test_verify_reaches_the_drive_over_rtu_too(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    bench = tmp_path / "rtu.toml"
    bench.write_text('name = "rtu"\ntransport = "modbus"\n[sim]\n[modbus]\nlink = "rtu"\n',
                     encoding="utf-8")
    code, match = _run(["verify", "SN123", "--bench", str(bench), "--db",
                        str(tmp_path / "s.db"), "--json"], monkeypatch, capsys)
    assert code == 1  # nothing recorded yet for this unit: no match, but the drive answered
    assert match["drive_trims"] == {"offset_a_mA": 0.0, "offset_b_mA": 0.0, "gain_a": 10000.0,
                                    "gain_b": 10000.0}


def test_a_recipe_that_needs_the_drive_angle_is_refused_before_anything_is_recorded(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    text = (Path(__file__).parents[1] / "recipes" / "default.toml").read_text(encoding="utf-8")
    text = text.replace('name = "default"', 'name = "angle"')
    recipe = tmp_path / "angle.toml"
    recipe.write_text(text[: text.index("[magnitude_sweep]")], encoding="utf-8")
    db = tmp_path / "station.db"
    code, doc = _run(["calibrate", "SN123", "--bench", "sim-modbus", "--recipe", str(recipe),
                      "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 2 and doc is None
    assert "magnitude_sweep" in LAST_STDERR[0]
    if db.exists():
        with Store(db) as store:
            assert not store.history("SN123")


class _Silencing:
    """Cuts the drive's Modbus link when the sweeps begin, as a pulled cable would."""

    def __init__(self) -> None:
        self.bench: SimBench | None = None

    def step(self, step: Step, detail: str) -> None:
        if step is Step.SWEEP and self.bench is not None and self.bench.modbus is not None:
            self.bench.modbus.silence()

    def progress(self, done: int, total: int) -> None:
        """Nothing to show."""


def test_a_drive_that_falls_silent_mid_run_is_an_error_and_ends_disabled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
) -> None:
    observer = _Silencing()
    states: list[DriveState] = []

    class Watched(SimBench):
        def start(self) -> None:
            super().start()
            observer.bench = self

        def close(self) -> None:
            # What a real drive does without its master: its watchdog disables it.
            deadline = time.monotonic() + 2 * self.config.modbus_watchdog_s + 1
            while self.drive.state is DriveState.OPERATION_ENABLED and time.monotonic() < deadline:
                time.sleep(0.05)
            states.append(self.drive.state)
            super().close()

    monkeypatch.setattr(simulator, "SimBench", Watched)
    station = Station(tmp_path / "station.db", benches.load_bench("sim-modbus"), "tester")
    result: Any = calibrate(station, "SN123", observer=observer)
    run = result.run
    assert run.verdict is Verdict.ERROR
    assert "drive" in run.reason and "no answer" in run.reason and "Modbus TCP" in run.reason
    assert run.trims_after is None
    assert states and states[0] is not DriveState.OPERATION_ENABLED
    with Store(tmp_path / "station.db") as store:
        (recorded,) = store.history("SN123")
    assert recorded.verdict is Verdict.ERROR and recorded.reason == run.reason
