"""``station sim record`` / ``sim unit``: ICD.md §5 recordings from the simulated bench."""

from __future__ import annotations

import json
import struct
import sys
import time
from collections.abc import Iterator
from copy import deepcopy
from dataclasses import replace
from itertools import pairwise
from pathlib import Path

import can
import pytest
from can.interfaces import virtual

from station.cli import main
from station.core import NOMINAL_TRIMS, Effect, LoadKind, Trims
from station.recording import LogFormat, read_metadata
from station.schedules import Hold, Phase, Schedule, ScheduleName, velocity_for
from station.serials import parse_serial
from station.sim.record import SimRecordRequest, record_schedule

# Hand-written from ICD.md, independent of the EDS files and the devices.
SYNC = 0x080
SENSOR_TPDO1 = 0x180 + 16
DRIVE_TPDO1 = 0x180 + 1
DRIVE_TPDO2 = 0x280 + 1
SENSOR_LAYOUT = struct.Struct("<Hhhh")
DRIVE1_LAYOUT = struct.Struct("<iHH")
DRIVE2_LAYOUT = struct.Struct("<hhHH")


def _short_schedule() -> Schedule:
    v = velocity_for(20.0, 256)
    trims = Trims(offset_a_mA=-120.0, offset_b_mA=55.0, gain_a=9500.0, gain_b=10500.0)
    return Schedule(
        "short",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 100),
            Hold(Phase.BASELINE, v, 1000, NOMINAL_TRIMS, 300),
            Hold(Phase.SWEEP_OFFSET_A, v, 1000, trims, 300),
            Hold(Phase.STOP, 0, 1000, trims, 50),
        ),
    )


def _request(out: Path, tmp_path: Path, **kw: object) -> SimRecordRequest:
    (tmp_path / "truth").mkdir(exist_ok=True)
    args: dict[str, object] = {
        "out": out,
        "serial": parse_serial("SN123"),
        "schedule": ScheduleName.CALIBRATION,
        "effects": frozenset(),
        "seed": 1,
        "load": LoadKind.DISK,
        "loss": 0.0,
        "truth": tmp_path / "truth" / f"{out.stem}.truth.json",
    }
    args.update(kw)
    return SimRecordRequest(**args)  # type: ignore[arg-type]


def _samples(path: Path) -> Iterator[tuple[int, dict[int, bytes]]]:
    """Group frames per SYNC as ICD.md §1 says: frames after SYNC n belong to sample n."""
    current: dict[int, bytes] | None = None
    counter = 0
    for msg in can.LogReader(str(path)):
        if msg.arbitration_id == SYNC:
            if current is not None:
                yield counter, current
            counter = msg.data[0]
            current = {}
        elif current is not None:
            current[msg.arbitration_id] = bytes(msg.data)
    if current is not None:
        yield counter, current


@pytest.mark.parametrize("fmt", list(LogFormat))
def test_recording_reads_back_and_matches_icd_byte_for_byte(tmp_path: Path, fmt: LogFormat) -> None:
    out = tmp_path / "rec" / f"run{fmt.value}"
    out.parent.mkdir()
    schedule = _short_schedule()
    result = record_schedule(_request(out, tmp_path), schedule)
    assert result.recording == out and out.exists()
    samples = list(_samples(out))
    assert len(samples) == schedule.cycles
    counters = [c for c, _ in samples]
    assert counters == [(n % 240) + 1 for n in range(len(counters))]
    sensor_counts = []
    positions = []
    trims_seen = []
    for _, frames in samples:
        # SDO traffic may sit between SYNCs too (ICD.md §5); each TPDO comes once.
        assert {SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2} <= set(frames)
        assert all(len(frames[cob]) == 8 for cob in (SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2))
        sensor_counts.append(SENSOR_LAYOUT.unpack(frames[SENSOR_TPDO1])[0])
        position, amplitude, _status = DRIVE1_LAYOUT.unpack(frames[DRIVE_TPDO1])
        assert amplitude == 1000
        positions.append(position)
        trims_seen.append(DRIVE2_LAYOUT.unpack(frames[DRIVE_TPDO2]))
    # The sensor counter advances one per SYNC.
    assert all((b - a) % 65536 == 1 for a, b in pairwise(sensor_counts))
    # At constant speed the position demand advances velocity x SYNC period per sample.
    steady = positions[250:390]
    slopes = {b - a for a, b in pairwise(steady)}
    assert slopes <= {20, 21}
    assert trims_seen[150] == (0, 0, 10000, 10000)
    assert trims_seen[500] == (-120, 55, 9500, 10500)
    meta = read_metadata(out)
    assert meta.serial == "SN123" and meta.rotor_teeth == 50
    assert meta.sensor_lsb_mps2 == pytest.approx(2 * 9.80665 / 32768, rel=1e-6)


def test_standstill_samples_see_gravity_on_z_and_nothing_tangential(tmp_path: Path) -> None:
    out = tmp_path / "rec" / "run.blf"
    out.parent.mkdir()
    record_schedule(_request(out, tmp_path), _short_schedule())
    lsb = read_metadata(out).sensor_lsb_mps2
    xyz = [SENSOR_LAYOUT.unpack(f[SENSOR_TPDO1])[1:] for _, f in list(_samples(out))[40:100]]
    z = sum(s[2] for s in xyz) / len(xyz) * lsb
    x = sum(s[0] for s in xyz) / len(xyz) * lsb
    assert z == pytest.approx(9.80665, abs=0.2)
    assert abs(x) < 0.2


def test_frame_loss_shows_as_sensor_counter_gaps(tmp_path: Path) -> None:
    out = tmp_path / "rec" / "run.csv"
    out.parent.mkdir()
    result = record_schedule(_request(out, tmp_path, loss=0.02), _short_schedule())
    assert 0.01 < 1 - result.frames_recorded / result.frames_seen < 0.03
    counters = [
        SENSOR_LAYOUT.unpack(bytes(m.data))[0]
        for m in can.LogReader(str(out))
        if m.arbitration_id == SENSOR_TPDO1
    ]
    gaps = sum((b - a) % 65536 - 1 for a, b in pairwise(counters))
    assert gaps > 0


def test_truth_file_names_effects_and_optimum_and_lives_apart(tmp_path: Path) -> None:
    out = tmp_path / "rec" / "run.log"
    out.parent.mkdir()
    result = record_schedule(
        _request(out, tmp_path, effects=frozenset({Effect.FLUX_HARMONICS})), _short_schedule()
    )
    truth = json.loads(result.truth.read_text())
    assert result.truth.parent != out.parent
    assert truth["effects"] == ["flux_harmonics"]
    assert set(truth["optimal_trims"]) == {"offset_a_mA", "offset_b_mA", "gain_a", "gain_b"}
    meta = json.loads(out.with_suffix(".json").read_text())
    assert "optimal_trims" not in meta and "effects" not in meta


def _run_cli(args: list[str], monkeypatch: pytest.MonkeyPatch) -> int:
    monkeypatch.setattr(sys, "argv", ["station", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    return int(stop.value.code or 0)


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--effect", "warp_drive"], "unknown effect 'warp_drive'"),
        (["--schedule", "sprint"], "sprint"),
        (["--serial", "../etc/passwd"], "malformed"),
    ],
)
def test_bad_sim_record_input_exits_2_and_writes_nothing(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    args: list[str],
    message: str,
) -> None:
    base = {"--serial": "SN5", "--schedule": "calibration"}
    extra: list[str] = []
    for key, value in zip(args[::2], args[1::2], strict=True):
        if key in base:
            base[key] = value
        else:
            extra += [key, value]
    out = tmp_path / "run.blf"
    argv = ["sim", "record", str(out), *[x for kv in base.items() for x in kv], *extra]
    assert _run_cli(argv, monkeypatch) == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


@pytest.mark.parametrize(
    ("name", "message"),
    [
        ("missing-dir/run.blf", "does not exist"),
        ("run.trc", "unknown recording suffix"),
        ("run.txt", "unknown recording suffix"),
    ],
)
def test_bad_output_path_exits_2_before_any_bus_traffic(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    name: str,
    message: str,
) -> None:
    code = _run_cli(
        ["sim", "record", str(tmp_path / name), "--serial", "SN5", "--schedule", "calibration"],
        monkeypatch,
    )
    assert code == 2
    assert message in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_unwritable_output_directory_exits_2(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    locked = tmp_path / "locked"
    locked.mkdir(mode=0o500)
    monkeypatch.setattr("os.access", lambda path, mode: False)
    code = _run_cli(
        ["sim", "record", str(locked / "run.asc"), "--serial", "SN5", "--schedule", "calibration"],
        monkeypatch,
    )
    assert code == 2
    assert "not writable" in capsys.readouterr().err
    assert list(locked.iterdir()) == []


def test_truth_beside_the_recording_is_refused(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    code = _run_cli(
        [
            "sim",
            "record",
            str(tmp_path / "run.asc"),
            "--serial",
            "SN5",
            "--schedule",
            "calibration",
            "--truth",
            str(tmp_path / "t.json"),
        ],
        monkeypatch,
    )
    assert code == 2
    assert "beside the recording" in capsys.readouterr().err


def test_sim_unit_reveals_optimum_and_effects_as_json(
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert (
        _run_cli(["sim", "unit", "SN123", "--effect", "detent_torque", "--json"], monkeypatch) == 0
    )
    doc = json.loads(capsys.readouterr().out)
    assert doc["serial"] == "SN123"
    assert set(doc["optimal_trims"]) == {"offset_a_mA", "offset_b_mA", "gain_a", "gain_b"}
    assert [e["id"] for e in doc["effects"]] == ["detent_torque"]


def test_sim_record_cli_records_the_calibration_schedule(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    out = tmp_path / "rec" / "SN77.mf4"
    out.parent.mkdir()
    code = _run_cli(
        [
            "sim",
            "record",
            str(out),
            "--serial",
            "SN77",
            "--schedule",
            "calibration",
            "--seed",
            "3",
            "--json",
        ],
        monkeypatch,
    )
    assert code == 0
    doc = json.loads(capsys.readouterr().out)
    assert doc["recording"] == str(out)
    assert Path(doc["truth"]).exists()
    assert out.exists() and out.with_suffix(".json").exists()
    syncs = sum(1 for m in can.LogReader(str(out)) if m.arbitration_id == SYNC)
    assert syncs == doc["cycles"]


def test_schedule_sensor_range_sets_the_recorded_lsb(tmp_path: Path) -> None:
    out = tmp_path / "rec" / "run.blf"
    out.parent.mkdir()
    schedule = replace(_short_schedule(), sensor_range_g=16)
    record_schedule(_request(out, tmp_path), schedule)
    assert read_metadata(out).sensor_lsb_mps2 == pytest.approx(16 * 9.80665 / 32768, rel=1e-6)


def test_unsupported_sensor_range_exits_2(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code = _run_cli(
        [
            "sim",
            "record",
            str(tmp_path / "run.asc"),
            "--serial",
            "SN5",
            "--schedule",
            "calibration",
            "--range-g",
            "3",
        ],
        monkeypatch,
    )
    assert code == 2
    assert "--range-g must be one of" in capsys.readouterr().err
    assert list(tmp_path.iterdir()) == []


def test_a_sync_is_recorded_before_the_answers_to_it_however_late_the_station_hears_itself(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """On a loaded machine the thread sending a SYNC can be preempted half-way through
    python-can's virtual send, which hands the frame to each bus on the channel in turn.
    Were the devices handed it before the station's own echo, their answers would be
    recorded ahead of their SYNC and every sample after would shift by one. Here each
    SYNC copy is slowed so far that the devices always answer within the gap."""
    def slow_sync_copy(msg: can.Message) -> can.Message:
        if msg.arbitration_id == SYNC:
            time.sleep(0.005)
        return deepcopy(msg)

    monkeypatch.setattr(virtual, "deepcopy", slow_sync_copy)
    out = tmp_path / "rec" / "run.blf"
    out.parent.mkdir()
    v = velocity_for(20.0, 256)
    schedule = Schedule(
        "tiny",
        (
            Hold(Phase.STANDSTILL, 0, 1000, NOMINAL_TRIMS, 20),
            Hold(Phase.BASELINE, v, 1000, NOMINAL_TRIMS, 40),
            Hold(Phase.STOP, 0, 1000, NOMINAL_TRIMS, 10),
        ),
    )
    record_schedule(_request(out, tmp_path), schedule)
    samples = list(_samples(out))
    assert len(samples) == schedule.cycles
    for _, frames in samples:
        assert {SENSOR_TPDO1, DRIVE_TPDO1, DRIVE_TPDO2} <= set(frames)


@pytest.mark.parametrize("command", [["sim", "record"], ["sim", "unit"]])
def test_effect_help_lists_every_effect_id(
    command: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setenv("COLUMNS", "400")
    monkeypatch.setattr(sys, "argv", ["station", *command, "--help"])
    with pytest.raises(SystemExit):
        main()
    shown = " ".join(capsys.readouterr().out.split())
    assert all(effect.value in shown for effect in Effect), shown
