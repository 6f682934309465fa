"""``station analyze RECORDING``: the CLI.md contract, on short simulated recordings."""

from __future__ import annotations

import json
import shutil
import sys
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import pytest

from station.cli import main
from station.core import NOMINAL_TRIMS, LoadKind, Trims
from station.recording import metadata_path_for
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

# Hand-written from ICD.md, independent of the reader.
SYNC = 0x080
SENSOR_TPDO1 = 0x180 + 16
TRIM_KEYS = {"offset_a_mA", "offset_b_mA", "gain_a", "gain_b"}
HOLD_CYCLES = 400  # 8 electrical periods at 20 Hz
PERIOD_S = 0.001
ELECTRICAL_PERIOD_S = 0.05


def _hold(
    phase: Phase, *, oa: int = 0, ob: int = 0, gain_a: int = 10000, cycles: int = HOLD_CYCLES
) -> Hold:
    trims = Trims(float(oa), float(ob), float(gain_a), float(20000 - gain_a))
    return Hold(phase, velocity_for(20.0, 256), 1000, trims, cycles)


def _short_calibration() -> Schedule:
    """The calibration experiment cut to its bones: two points per sweep plus the baseline,
    enough for both estimators (three distinct values along every axis)."""
    return Schedule(
        "short-calibration",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 100),
            # The baseline hold also carries the ramp up to speed: give it room to settle.
            _hold(Phase.BASELINE, cycles=2 * HOLD_CYCLES),
            _hold(Phase.SWEEP_OFFSET_A, oa=-200),
            _hold(Phase.SWEEP_OFFSET_A, oa=200),
            _hold(Phase.SWEEP_OFFSET_B, ob=-200),
            _hold(Phase.SWEEP_OFFSET_B, ob=200),
            _hold(Phase.SWEEP_GAIN, gain_a=8500),
            _hold(Phase.SWEEP_GAIN, gain_a=11500),
            Hold(Phase.STOP, 0, 1000, NOMINAL_TRIMS, 50),
        ),
        sensor_range_g=8,
    )


def _standing_still() -> Schedule:
    """The drive is enabled and its trims change, but it never turns."""
    still = Trims(-200.0, 0.0, 10000.0, 10000.0)
    return Schedule(
        "standstill",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 500),
            Hold(Phase.SWEEP_OFFSET_A, 0, 1000, still, 500),
        ),
    )


@dataclass(frozen=True)
class Recordings:
    calibration: Path
    standstill: Path


@pytest.fixture(scope="module")
def recordings(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Recordings]:
    root = tmp_path_factory.mktemp("analyze")
    (root / "rec").mkdir()
    (root / "truth").mkdir()

    def record(name: str, schedule: Schedule) -> Path:
        out = root / "rec" / name
        request = SimRecordRequest(
            out=out,
            serial=parse_serial("SN123"),
            schedule=ScheduleName.CALIBRATION,  # validated only; `schedule` runs
            effects=frozenset(),
            seed=1,
            load=LoadKind.DISK,
            loss=0.0,  # a lossless log reads back the same every run: exact expectations
            truth=root / "truth" / f"{out.stem}.truth.json",
        )
        return record_schedule(request, schedule).recording

    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("STATION_HOME", str(root / "home"))
        yield Recordings(
            record("calibration.blf", _short_calibration()),
            record("standstill.blf", _standing_still()),
        )


def _run(args: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(sys, "argv", ["station", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    return int(stop.value.code or 0)


def _analyze_json(
    path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str], *extra: str
) -> dict[str, Any]:
    assert _run(["analyze", str(path), "--json", *extra], monkeypatch) == 0
    doc: dict[str, Any] = json.loads(capsys.readouterr().out)
    return doc


def _copy(src: Path, dst_dir: Path, name: str | None = None) -> Path:
    """The log and its metadata under a new name (same stem for both)."""
    dst = dst_dir / (name or src.name)
    shutil.copyfile(src, dst)
    shutil.copyfile(metadata_path_for(src), metadata_path_for(dst))
    return dst


def _metadata(path: Path) -> dict[str, Any]:
    doc: dict[str, Any] = json.loads(metadata_path_for(path).read_text(encoding="utf-8"))
    return doc


def _write_metadata(path: Path, doc: dict[str, Any]) -> None:
    metadata_path_for(path).write_text(json.dumps(doc), encoding="utf-8")


def _filtered(src: Path, dst: Path, keep: Callable[[can.Message], bool]) -> Path:
    """Another logger's view of the same run: only the frames ``keep`` lets through."""
    writer = can.Logger(str(dst))
    try:
        for msg in can.LogReader(str(src)):
            if keep(msg):
                writer.on_message_received(msg)
    finally:
        writer.stop()
    doc = _metadata(src)
    doc.pop("frames_recorded", None)  # another bench need not write it
    _write_metadata(dst, doc)
    return dst


# ---------------------------------------------------------------------------- success


def test_json_gives_trims_segment_count_and_method(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _analyze_json(recordings.calibration, monkeypatch, capsys)
    assert set(doc["trims"]) == TRIM_KEYS
    assert all(isinstance(v, float) for v in doc["trims"].values())
    assert isinstance(doc["segments"], int) and not isinstance(doc["segments"], bool)
    assert doc["segments"] == 7  # baseline and six sweep points
    assert doc["method"] == "coherent"
    assert doc["trims"]["gain_a"] + doc["trims"]["gain_b"] == pytest.approx(20000.0)
    assert doc["serial"] == "SN123"


def test_human_output_shows_the_trims(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    trims = _analyze_json(recordings.calibration, monkeypatch, capsys)["trims"]
    assert _run(["analyze", str(recordings.calibration)], monkeypatch) == 0
    out = capsys.readouterr().out
    for key, value in trims.items():
        assert key in out
        assert f"{value:.1f}" in out
    assert "coherent" in out


def test_paper_method_is_used_when_asked_for(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    doc = _analyze_json(recordings.calibration, monkeypatch, capsys, "--method", "paper")
    assert doc["method"] == "paper"
    assert set(doc["trims"]) == TRIM_KEYS
    assert [p["axis"] for p in doc["fit"]["parabolas"]] == [
        "offset_a_mA", "offset_b_mA", "gain_split"
    ]
    # The schedule sweeps the split at offsets 0, not at their optimum: said, not hidden.
    assert any("gain_split: swept with the offsets" in w for w in doc["warnings"])


def test_a_fixed_settling_drops_that_many_periods_after_each_change(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    judged = _analyze_json(recordings.calibration, monkeypatch, capsys)
    fixed = _analyze_json(recordings.calibration, monkeypatch, capsys, "--settle-periods", "2")
    assert fixed["segments"] == judged["segments"]
    settled = [p["settled_after_s"] for p in fixed["conditions"][0]["points"]]
    # Every sweep point starts at a trim change and lasts whole periods: exactly two go.
    assert settled[1:] == pytest.approx([2 * ELECTRICAL_PERIOD_S] * 6, abs=PERIOD_S / 2)
    # The baseline starts after the speed ramp; its end, not its start, is on the period grid.
    assert 2 * ELECTRICAL_PERIOD_S - PERIOD_S / 2 <= settled[0] < 3 * ELECTRICAL_PERIOD_S
    assert [p["settled_after_s"] for p in judged["conditions"][0]["points"]] != settled
    assert abs(fixed["trims"]["offset_a_mA"] - judged["trims"]["offset_a_mA"]) < 5.0


# ----------------------------------------------------------------------- input errors


def _refused(
    args: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> str:
    """Exit code 2, nothing on stdout (even with --json), and the message on stderr."""
    assert _run(["analyze", *args, "--json"], monkeypatch) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    return " ".join(captured.err.split())  # the console may wrap a long message


def test_missing_metadata_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = tmp_path / "run.blf"
    shutil.copyfile(recordings.calibration, log)
    err = _refused([str(log)], monkeypatch, capsys)
    assert "metadata file run.json is missing" in err


@pytest.mark.parametrize("key", ["rotor_teeth", "sync_period_s", "tangential_axis"])
def test_metadata_without_a_required_key_names_the_key(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str], key: str,
) -> None:
    log = _copy(recordings.calibration, tmp_path)
    doc = _metadata(log)
    del doc[key]
    _write_metadata(log, doc)
    assert f"missing key '{key}'" in _refused([str(log)], monkeypatch, capsys)


@pytest.mark.parametrize(
    "entry", [("sync_period_s", "fast"), ("drive_node", 1.5), ("microsteps_per_fullstep", None)]
)
def test_metadata_with_a_malformed_value_names_the_key(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str], entry: tuple[str, object],
) -> None:
    key, value = entry
    log = _copy(recordings.calibration, tmp_path)
    doc = _metadata(log)
    doc[key] = value
    _write_metadata(log, doc)
    err = _refused([str(log)], monkeypatch, capsys)
    assert f"key '{key}' has a malformed value" in err


def test_metadata_that_is_not_json_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _copy(recordings.calibration, tmp_path)
    metadata_path_for(log).write_text('{"format": "hsm-recording/1", ', encoding="utf-8")
    assert "metadata is not valid JSON" in _refused([str(log)], monkeypatch, capsys)


def test_an_unknown_suffix_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _copy(recordings.calibration, tmp_path, "run.trc")
    assert "unknown recording suffix '.trc'" in _refused([str(log)], monkeypatch, capsys)


def test_a_log_without_sync_frames_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _filtered(recordings.calibration, tmp_path / "nosync.blf",
                    lambda m: m.arbitration_id != SYNC)
    assert "holds no SYNC" in _refused([str(log)], monkeypatch, capsys)


def test_a_log_without_sensor_frames_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _filtered(recordings.calibration, tmp_path / "nosensor.blf",
                    lambda m: m.arbitration_id != SENSOR_TPDO1)
    assert "holds no sensor TPDO1" in _refused([str(log)], monkeypatch, capsys)


def test_a_truncated_log_is_refused(
    recordings: Recordings, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    log = _copy(recordings.calibration, tmp_path)
    data = log.read_bytes()
    log.write_bytes(data[: len(data) // 2])
    assert "truncated" in _refused([str(log)], monkeypatch, capsys)


def test_a_drive_that_never_moves_gives_no_steady_segment(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused([str(recordings.standstill)], monkeypatch, capsys)
    assert "no steady segment" in err


def test_a_missing_recording_is_refused(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused([str(tmp_path / "nowhere.blf")], monkeypatch, capsys)
    assert "nowhere" in err


def test_an_unknown_method_is_a_usage_error(
    recordings: Recordings, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    err = _refused([str(recordings.calibration), "--method", "guess"], monkeypatch, capsys)
    assert "guess" in err


def test_a_recording_that_does_not_exist_is_named_as_such(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    err = _refused([str(tmp_path / "nope.blf")], monkeypatch, capsys)
    assert "nope.blf: no such recording" in err and "metadata" not in err
