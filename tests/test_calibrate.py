"""``station calibrate`` and field service end to end on the simulated bench.

Every verdict path the operator can meet: a unit that passes (and lands on
the plant's own optimum), a unit that fails a limit (after its trims were
stored, and before, when the estimate is out of bounds), and station errors
(the wrong unit on the fixture, a sensor that fails its self-check, Ctrl-C
mid-sweep). Each run must be in the database with what it learnt; the drive
must be left disabled whatever happened.
"""

from __future__ import annotations

import json
import re
import subprocess
import sys
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from drivers.base import DriveState, decode_statusword
from station import __version__, benches
from station.cli import main
from station.core import STANDARD_GRAVITY, LoadKind, Trims
from station.limits import trims_within
from station.physics.optimum import optimal_trims, steady_harmonics, steady_reading
from station.recipes import load_recipe
from station.recording import read_metadata
from station.runs import LimitName, Run, Verdict
from station.serials import parse_serial
from station.service import Station, calibrate
from station.sim import bench as simulator
from station.sim.bench import SimBench
from station.sim.population import LineKind, draw_line_unit
from station.sim.record import describe_unit
from station.simsettings import SimSettings
from station.steps import Step
from station.store import Store
from tests.cli import run_cli

OFFSET_TOLERANCE_mA = 3.0
GAIN_TOLERANCE = 30.0
CLI_KEYS = {"run_id", "serial", "verdict", "trims", "before", "after", "failed_limits",
            "recording"}
TRIM_KEYS = {"offset_a_mA", "offset_b_mA", "gain_a", "gain_b"}
NOMINAL = {"offset_a_mA": 0.0, "offset_b_mA": 0.0, "gain_a": 10000.0, "gain_b": 10000.0}


def _run(args: list[str], monkeypatch: pytest.MonkeyPatch,
         capsys: pytest.CaptureFixture[str]) -> tuple[int, Any]:
    """The CLI in-process (``tests.cli``); returns the exit code and the parsed JSON on
    stdout (or None).

    What went to stderr stays readable as ``LAST_STDERR[0]``, unwrapped.
    """
    outcome = run_cli(args, monkeypatch, capsys)
    LAST_STDERR[0] = outcome.stderr
    return outcome.code, outcome.doc if outcome.stdout.strip() else None


LAST_STDERR = [""]


def _recipe_variant(folder: Path, name: str, *, without: str | None = None,
                    **values: float) -> Path:
    """The default recipe under another name, with some ``key = value`` lines changed
    and the table ``without`` left out."""
    text = (Path(__file__).parents[1] / "recipes" / "default.toml").read_text(encoding="utf-8")
    text = text.replace('name = "default"', f'name = "{name}"')
    if without is not None:
        text, count = re.subn(rf"(?ms)^\[{without}\]\n.*?(?=^\[)", "", text)
        assert count == 1, without
    for key, value in values.items():
        text, count = re.subn(rf"(?m)^{key} = [^#\n]*", f"{key} = {value!r}", text)
        assert count == 1, key
    path = folder / f"{name}.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _bench_file(folder: Path, name: str, body: str) -> Path:
    path = folder / f"{name}.toml"
    path.write_text(f'name = "{name}"\nstation_id = 7\n{body}', encoding="utf-8")
    return path


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "results" / "station.db"


def test_calibrate_passes_on_the_optimum_and_verify_and_history_agree(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, doc = _run(["calibrate", "SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0, doc["reason"]
    assert doc.keys() >= CLI_KEYS
    assert doc["verdict"] == "pass" and doc["failed_limits"] == []
    assert set(doc["trims"]) == TRIM_KEYS
    assert set(doc["before"]) == set(doc["after"]) == {"h1", "h2"}
    assert doc["after"]["h1"] < doc["before"]["h1"] / 10
    truth = describe_unit(parse_serial("SN123"))["optimal_trims"]
    for key in ("offset_a_mA", "offset_b_mA"):
        assert abs(doc["trims"][key] - truth[key]) <= OFFSET_TOLERANCE_mA
    for key in ("gain_a", "gain_b"):
        assert abs(doc["trims"][key] - truth[key]) <= GAIN_TOLERANCE
    # The run is kept as an ICD recording beside the database, with its hash in the record.
    recording = Path(doc["recording"])
    assert recording.parent.parent == db.parent / "recordings"
    assert read_metadata(recording).serial == "SN123"
    assert len(doc["recording_sha256"]) == 64

    # A new process reads the unit's EEPROM back and finds what the database says.
    verified = subprocess.run(
        [sys.executable, "-m", "station.cli", "verify", "SN123", "--db", str(db), "--json"],
        capture_output=True, text=True, check=False,
    )
    assert verified.returncode == 0, verified.stderr
    match = json.loads(verified.stdout)
    assert match["match"] is True
    assert match["drive_trims"] == match["recorded_trims"] == doc["trims"]
    assert match["calibration_record"]["count"] == 1

    code, runs = _run(["history", "SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0
    assert [r["run_id"] for r in runs] == [doc["run_id"]]
    assert {"run_id", "started_at", "verdict", "trims", "recipe", "station"} <= runs[0].keys()
    assert runs[0]["recipe"] == "default" and runs[0]["station"] == 1


def test_a_limit_the_unit_cannot_meet_fails_the_unit_and_is_recorded(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _recipe_variant(tmp_path, "hushed", max_h1_after_mps2=1e-5)
    code, doc = _run(["calibrate", "SN123", "--recipe", str(recipe), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 1
    assert doc["verdict"] == "fail"
    assert [c["name"] for c in doc["failed_limits"]] == ["h1_after_mps2"]
    assert doc["failed_limits"][0]["high"] == 1e-5
    assert "h1_after_mps2" in doc["reason"]
    # The trims were stored (they are the unit's best), but no calibration record was.
    code, match = _run(["verify", "SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0 and match["drive_trims"] == doc["trims"]
    assert match["calibration_record"]["count"] == 0
    with Store(db) as store:
        (run,) = store.history("SN123")
    assert run.verdict is not None and run.verdict.value == "fail"
    assert run.recipe.name == "hushed" and run.recipe.sha256 == load_recipe(recipe).sha256


def _drawn_station(db: Path, seed: int) -> tuple[Station, str]:
    """A station whose simulated fixture holds the wide population's unit of ``seed``."""
    unit = draw_line_unit(seed).unit
    sim = replace(benches.SIM_SPEC.sim or SimSettings(), drawn=unit)
    return Station(db, replace(benches.SIM_SPEC, sim=sim), "bench"), unit.serial


def _assert_on_the_plants_optimum(run: Run, seed: int) -> None:
    """The run's estimate within issue 16's 1 mA and 10 gain units of the plant's optimum."""
    truth, got = optimal_trims(draw_line_unit(seed).unit), run.trims_estimated
    assert got is not None
    assert abs(got.offset_a_mA - truth.offset_a_mA) < 1.0
    assert abs(got.offset_b_mA - truth.offset_b_mA) < 1.0
    assert abs(got.gain_a - truth.gain_a) < 10.0


def test_a_unit_of_the_wide_population_lands_on_its_plants_optimum(db: Path) -> None:
    # Seed 1000: a belt with load friction and an eccentric rotor, unlike any serial's unit.
    assert draw_line_unit(1000).unit.load is LoadKind.BELT
    station, serial = _drawn_station(db, 1000)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    _assert_on_the_plants_optimum(run, 1000)
    with Store(db) as store:
        (kept,) = store.history(serial)
    assert kept.serial == serial
    # Its baseline grazed the range once: said, and shown in the table.
    assert _clipped(kept) == (1, 1)


@pytest.mark.parametrize("seed", [
    2007,  # detent torque and a saturating iron
    2012,  # reluctance torque, a sensor clock 455 ppm slow
    2017,  # rough: offsets -191/+212 mA, gains 13 % apart, four concealed effects
    2024,  # flux harmonics and a load resonance
])
def test_belt_units_pass_within_a_milliampere_of_their_plants_optimum(db: Path, seed: int) -> None:
    line = draw_line_unit(seed)
    assert line.unit.load is LoadKind.BELT
    station, serial = _drawn_station(db, seed)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert run.trims_stored
    _assert_on_the_plants_optimum(run, seed)


@pytest.mark.parametrize("modbus", [False, True])
def test_a_sensor_on_its_own_clock_is_followed_sample_by_sample(db: Path, modbus: bool) -> None:
    # Seed 5020: detent torque puts tens of m/s² into orders 4-12 and the sensor runs
    # 226 ppm fast, so it skips a sample every 4.4 s. Demodulated on the SYNC's instants,
    # a skipped sample read a 0.15 m/s² H1 as 1.16 and the estimate was 1.4 mA off.
    line = draw_line_unit(5020)
    ppm = line.unit.sensor.clock_drift_ppm
    assert -230 < ppm < -220
    spec = benches.SIM_MODBUS_SPEC if modbus else benches.SIM_SPEC
    sim = replace(spec.sim or SimSettings(), drawn=line.unit)
    run = calibrate(Station(db, replace(spec, sim=sim), "bench"), line.unit.serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert run.fit is not None
    clock = run.fit["sensor_clock"]
    assert abs(clock["ppm"] - ppm) < 15
    # Over CANopen a skip fell in a measured stretch; the Modbus holds measure 3 of their
    # 7 periods, and on this unit no skip fell in one.
    assert clock["wraps"] == (0 if modbus else 1)
    # Over CANopen the phasors time it too, and put every hold on it.
    assert ("phasors_ppm" in clock) is not modbus
    if not modbus:
        assert abs(clock["phasors_ppm"] - ppm) < 15
    _assert_on_the_plants_optimum(run, 5020)


@pytest.mark.parametrize(("seed", "ppm"), [
    (725234896, -322),  # a belt with a load resonance: no hold could time its clock
    (1728856850, 0),  # a belt with friction and an eccentric rotor, and no clock at all
])
def test_a_belt_whose_holds_ring_has_its_clock_timed_by_the_phasors(db: Path, seed: int,
                                                                     ppm: int) -> None:
    # A belt's holds ring after every step, and most time the clock to no better than
    # ±1000 ppm; but a clock turns every later hold's phasors in proportion to its |H|,
    # which the trims cannot explain: the phasors time it. An eccentric rotor turns them
    # too, with the rotor's angle: it is modelled, not taken for a clock. (725234896's
    # holds pooled by their median alone timed no clock; weighed by their precision, the
    # few that settled time it too.)
    line = draw_line_unit(seed)
    assert line.unit.load is LoadKind.BELT
    assert line.unit.sensor.clock_drift_ppm == pytest.approx(ppm, abs=0.5)
    station, serial = _drawn_station(db, seed)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert run.fit is not None
    clock = run.fit["sensor_clock"]
    truth = line.unit.sensor.clock_drift_ppm
    assert clock["ppm"] == 0.0 or abs(clock["ppm"] - truth) < 15
    assert abs(clock["phasors_ppm"] - truth) < 15
    _assert_on_the_plants_optimum(run, seed)


def test_a_unit_still_ringing_after_its_reset_is_measured_until_it_has_settled(
        db: Path) -> None:
    # Population seed 100830014: a detent disk whose start from standstill after the
    # reset rings down across the verification's first hold, which read 0.114 m/s² of H1
    # against the limit of 0.08 where its steady state, at the trims stored, is 0.015.
    station, serial = _drawn_station(db, 100830014)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert any(w.startswith("verify: the unit was still settling after its reset")
               for w in run.warnings), run.warnings
    assert run.after is not None and run.after.h1 < 0.04
    _assert_on_the_plants_optimum(run, 100830014)


def test_a_belt_ringing_through_every_hold_has_its_ring_fitted_out(db: Path) -> None:
    # Population seed 2046250336: a belt whose load mode near 20 Hz rings after every
    # trim step through each hold (its halves 11-22 σ apart); left in, the estimate was
    # 9.8 mA off with σ 3.9 mA and the unit failed.
    line = draw_line_unit(2046250336)
    assert line.unit.load is LoadKind.BELT
    station, serial = _drawn_station(db, 2046250336)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    truth, got = optimal_trims(line.unit), run.trims_estimated
    assert got is not None
    assert abs(got.offset_a_mA - truth.offset_a_mA) < 2.0
    assert abs(got.offset_b_mA - truth.offset_b_mA) < 2.0
    assert abs(got.gain_a - truth.gain_a) < 10.0


def test_a_belt_whose_rounds_share_one_split_near_the_null_is_judged_on_a_real_sweep(
    db: Path,
) -> None:
    # Population seed 717580667: magnetic saturation and reluctance torque on a belt, whose
    # H2 bends across the first round's split steps. Only the least-shaken points fit
    # within the noise, and those held splits 2 units apart: their H2 fit's R² of 0.34
    # failed the unit, though its estimate was 1.2 mA and 0.6 gain units from the optimum.
    line = draw_line_unit(717580667)
    assert line.unit.load is LoadKind.BELT
    station, serial = _drawn_station(db, 717580667)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    (r_squared,) = [c for c in run.limits if c.name is LimitName.FIT_R2]
    assert r_squared.passed and r_squared.value is not None and r_squared.value > 0.99
    assert run.fit is not None and all(fit["points_used"] > 5 for fit in run.fit["fits"])
    truth, got = optimal_trims(line.unit), run.trims_estimated
    assert got is not None
    assert abs(got.offset_a_mA - truth.offset_a_mA) < 2.0
    assert abs(got.offset_b_mA - truth.offset_b_mA) < 2.0
    assert abs(got.gain_a - truth.gain_a) < 10.0


def _steady(seed: int, trims: Trims) -> tuple[float, float]:
    """The plant's own steady |H1| and |H2| at ``trims`` (the default recipe's 1 A, 20 Hz)."""
    h = steady_harmonics(draw_line_unit(seed).unit, trims, amplitude_mA=1000.0,
                         electrical_hz=20.0)
    return abs(h[0]), abs(h[1])


@pytest.mark.parametrize("corrections", [1, 0])
def test_a_verification_over_its_limit_corrects_the_trims_from_its_own_phasors(
    db: Path, tmp_path: Path, corrections: int,
) -> None:
    # Population seed 1405145028: a belt near resonance, 0.12 m/s² of H1 per mA. The sweep's
    # estimate was 0.36 / 0.47 mA off, the drive's whole milliamperes 0.55 / 0.88, and the
    # verification read 0.10 m/s² against a limit of 0.08, as the plant has it there.
    recipe = _recipe_variant(tmp_path, "corrects", max_corrections=corrections)
    station, serial = _drawn_station(db, 1405145028)
    run = calibrate(station, serial, str(recipe)).run
    estimate, shipped = run.trims_estimated, run.trims_after
    assert estimate is not None and shipped is not None
    said = [w for w in run.warnings if "verified again" in w]
    if not corrections:
        # The recipe allows none: judged on the one verification, the trims stay stored.
        assert run.verdict is Verdict.FAIL and not said
        assert shipped == estimate.rounded()
        (h1,) = [c for c in run.limits if c.name is LimitName.H1_AFTER]
        assert h1.passed is False
        return
    assert run.verdict is Verdict.PASS, run.reason
    assert len(said) == 1 and "h1_after_mps2 over the limit" in said[0]
    assert shipped != estimate.rounded()
    before, after = _steady(1405145028, estimate.rounded()), _steady(1405145028, shipped)
    assert before[0] > 0.08 and after[0] < 0.06
    assert run.after is not None and run.after.h1 < 0.08


def test_a_ring_far_from_the_low_orders_is_not_read_as_ripple_by_the_verification(
    db: Path,
) -> None:
    # Population seed 1552235132: a disk's 99 Hz mode, rung by the start after the reset,
    # leaked 0.08 m/s² into H1 through a flat window where the unit had 0.032; it failed.
    station, serial = _drawn_station(db, 1552235132)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert not any("verified again" in w for w in run.warnings)
    assert run.after is not None and run.trims_after is not None
    steady = _steady(1552235132, run.trims_after)
    assert abs(run.after.h1 - steady[0]) < 0.02 and abs(run.after.h2 - steady[1]) < 0.03


def test_a_clock_two_holds_timed_closely_is_the_runs_clock(db: Path) -> None:
    # Population seed 508770410: a rough belt with a 215 ppm sensor clock that two holds
    # timed to 10 ppm and seven others loosely. Taken for no clock, its unplaced wrap put
    # 0.17 m/s² of H1 into the verification of a unit with 0.003.
    line = draw_line_unit(508770410)
    station, serial = _drawn_station(db, 508770410)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert run.fit is not None
    assert run.fit["sensor_clock"]["ppm"] == pytest.approx(line.unit.sensor.clock_drift_ppm,
                                                           abs=40.0)
    _assert_on_the_plants_optimum(run, 508770410)


def test_a_fallback_neighbourhood_is_the_one_that_determines_the_null_best(db: Path) -> None:
    # Population seed 879511937: a belt with reluctance torque and an eccentric rotor, whose
    # no neighbourhood of least-shaken points fits within the noise. The smallest that
    # determined the maps left it 5.7 mA and 81 gain units off, σ 4 mA: a FAIL.
    station, serial = _drawn_station(db, 879511937)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert any("fit worse than the noise" in w for w in run.warnings)
    _assert_on_the_plants_optimum(run, 879511937)


def test_a_recipe_without_a_clipping_policy_uses_clipped_holds_and_says_so(
    db: Path, tmp_path: Path,
) -> None:
    # Population seed 553880387: a light disk whose untrimmed ripple clips ±4 g; it passed
    # with nothing in its record saying so before the station counted clipped samples.
    recipe = _recipe_variant(tmp_path, "narrow", without="clipping", sensor_range_g=4)
    station, serial = _drawn_station(db, 553880387)
    run = calibrate(station, serial, str(recipe)).run
    shown, said = _clipped(run, 4)
    assert shown == said > 100
    assert not any("measured again" in w or "left out:" in w for w in run.warnings)


def test_a_hold_clipped_beyond_its_share_is_measured_again_nearer_the_centre(
    db: Path, tmp_path: Path,
) -> None:
    # Population seed 1664852622: a rough light disk (offsets -229/-154 mA, detent and flux
    # harmonics) whose first star step clips ±16 g in 2 % of one hold. At ±4 g, 6,110
    # samples clipped and the estimate was 187 mA off.
    recipe = _recipe_variant(tmp_path, "strict", max_share=0.01)
    station, serial = _drawn_station(db, 1664852622)
    run = calibrate(station, serial, str(recipe)).run
    again = [w for w in run.warnings if "more than 1% of their samples: measured again at "
             "0.5 of their step" in w]
    assert again
    (check,) = [c for c in run.limits if c.name is LimitName.CLIPPED]
    assert "measured again nearer the centre" in check.note
    _assert_on_the_plants_optimum(run, 1664852622)
    # Its flux harmonics leave 0.54 m/s² of H2 at the optimum: a true FAIL, on that alone.
    assert run.verdict is Verdict.FAIL
    assert {c.name for c in run.failed_limits} == {LimitName.H2_AFTER}


def test_a_unit_too_rough_for_the_sensor_fails_saying_so_with_its_trims_untouched(
    db: Path,
) -> None:
    # Population seed 7148: detent and flux harmonics on a light disk put peaks of 1.7
    # times ±16 g into its untrimmed ripple; its baseline and both gain steps clip in
    # more than a fifth of their samples however near the centre they are measured.
    station, serial = _drawn_station(db, 7148)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.FAIL
    assert run.reason is not None and "because the ripple clipped the sensor's ±16 g" in run.reason
    assert any("left out: clipped" in w for w in run.warnings)
    assert not run.trims_stored and run.trims_after is None
    with Store(db) as store:
        (kept,) = store.history(serial)
    assert kept.verdict is Verdict.FAIL and kept.reason == run.reason
    assert kept.trims_before == Trims()


@pytest.mark.parametrize("rounds", [2, 0])
def test_a_unit_short_of_information_is_measured_until_its_sigma_is_within_the_limit(
    db: Path, tmp_path: Path, rounds: int,
) -> None:
    # Population seed 1874937362: a belt whose maps hold over its 7 least-shaken points of
    # 25; after three rounds its offsets' σ was 4.4 mA against a limit of 3.
    recipe = _recipe_variant(tmp_path, "sigma", sigma_rounds=rounds)
    station, serial = _drawn_station(db, 1874937362)
    run = calibrate(station, serial, str(recipe)).run
    added = [w for w in run.warnings if "after 3 rounds: one more of" in w]
    if not rounds:
        assert run.verdict is Verdict.FAIL and not added
        assert {c.name for c in run.failed_limits} == {LimitName.OFFSET_SIGMA}
        return
    assert run.verdict is Verdict.PASS, run.reason
    assert added and added[0].startswith("sweep_star: offset σ ")
    assert run.uncertainty is not None and run.uncertainty.offset_a_mA <= 3.0
    _assert_on_the_plants_optimum(run, 1874937362)


def test_a_unit_whose_ripple_peaks_over_the_rail_at_every_trim_fails_saying_so(db: Path) -> None:
    # Population seed 1742693704: flux harmonics and current distortion peak over ±16 g at
    # the same phase of every period whatever the trims. The fit never saw those phases:
    # it read H1 0.014 m/s² where the plant has 0.42, and the unit passed 15 mA off.
    unit = draw_line_unit(1742693704).unit
    reading, _ = steady_reading(unit, optimal_trims(unit))
    assert np.abs(reading).max() > 16 * STANDARD_GRAVITY  # even at its optimum
    station, serial = _drawn_station(db, 1742693704)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.FAIL
    assert run.reason is not None
    assert "the ripple over the sensor's ±16 g hides part of each harmonic" in run.reason
    assert any(w.startswith("clipping: ") for w in run.warnings)
    assert {c.name for c in run.failed_limits} == {LimitName.OFFSET_SIGMA, LimitName.GAIN_SIGMA}
    assert not run.trims_stored and run.trims_after is None


def test_a_verification_between_two_of_the_clock_s_wraps_reads_the_unit_as_it_is(
    db: Path,
) -> None:
    # Population seed 1268081785: a detent disk whose sensor runs 214 ppm fast. The
    # run's clock, anchored on the one wrap a sweep hold placed, put the next wrap 117
    # samples into the verification, where the waveform has none: the unit, stored 0.1
    # mA from its optimum, read H1 0.60 and H2 0.74 m/s² after and failed both limits.
    station, serial = _drawn_station(db, 1268081785)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.PASS, run.reason
    assert run.fit is not None and run.fit["sensor_clock"]["wraps"] >= 1
    assert run.after is not None and run.after.h1 < 0.08 and run.after.h2 < 0.25
    _assert_on_the_plants_optimum(run, 1268081785)


def _clipped(run: Run, range_g: int = 16) -> tuple[int, int]:
    """Samples at full scale as the limit table shows them (a count judged by no limit),
    and as the warnings say them."""
    (check,) = [c for c in run.limits if c.name is LimitName.CLIPPED]
    assert check.passed is None and check.value is not None
    assert ("left out of the fits" in check.note) == (check.value > 0)
    said = [w for w in run.warnings if f"samples clipped at the sensor's ±{range_g} g" in w]
    return int(check.value), sum(int(w.split(": ")[1].split()[0]) for w in said)


def test_a_unit_whose_amplifier_no_recipe_can_trim_fails_on_the_bound_untouched(
    db: Path,
) -> None:
    # Seed 41: a disk whose phase A is 367 mA off, beyond the default recipe's ±250 mA.
    line = draw_line_unit(41)
    assert line.kind is LineKind.OUT_OF_BOUNDS
    assert not trims_within(load_recipe("default").limits, optimal_trims(line.unit))
    station, serial = _drawn_station(db, 41)
    run = calibrate(station, serial).run
    assert run.verdict is Verdict.FAIL
    assert LimitName.OFFSET_A in {check.name for check in run.failed_limits}
    assert not run.trims_stored and run.trims_after is None


def test_trims_outside_the_recipe_bounds_are_never_written(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _recipe_variant(tmp_path, "narrow", offset_bound_mA=20.0)
    code, doc = _run(["calibrate", "SN123", "--recipe", str(recipe), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 1
    assert {c["name"] for c in doc["failed_limits"]} == {"offset_a_mA", "offset_b_mA"}
    assert doc["trims"] is None and doc["after"] is None
    assert doc["trims_estimated"] is not None
    code, match = _run(["verify", "SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 1  # nothing was ever stored for this unit
    assert match["drive_trims"] == NOMINAL and match["recorded_trims"] is None
    # Field service finds its history, and is told why none of it counts as a calibration.
    code, again = _run(["recalibrate", "SN123", "--reason", "field return", "--db", str(db),
                        "--json"], monkeypatch, capsys)
    assert code == 2 and again is None
    said = LAST_STDERR[0]
    assert "1 run(s)" in said and "none stored trims" in said and "fail" in said
    assert "station calibrate SN123" in said and "--force" in said


def test_the_wrong_unit_on_the_fixture_exits_2_with_nothing_recorded_or_written(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str], drive_states_at_close: list[DriveState],
) -> None:
    bench = _bench_file(tmp_path, "swapped", '[sim]\nunit = "SN124"\n')
    code, doc = _run(["calibrate", "SN123", "--bench", str(bench), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 2 and doc is None
    assert "reports serial SN124" in LAST_STDERR[0]
    with Store(db) as store:
        assert store.history("SN123") == [] and store.history("SN124") == []
    assert not (db.parent / "recordings" / "SN123").exists() or not any(
        (db.parent / "recordings" / "SN123").iterdir())
    # The unit on the fixture still holds its factory trims, untouched.
    code, match = _run(["verify", "SN124", "--db", str(db), "--json"], monkeypatch, capsys)
    assert match["drive_trims"] == NOMINAL
    assert drive_states_at_close[0] is not DriveState.OPERATION_ENABLED


@pytest.mark.parametrize(
    ("bench_body", "reason"),
    [
        ("[sim]\nnoise_ug = 20000\n", "noise"),
        ('[sim]\n[fixture]\ntangential_axis = "y"\ngravity_axis = "x"\nradius_m = 0.04\n'
         "gear_ratio = 1.0\n", "gravity"),
    ],
    ids=["noisy-sensor", "sensor-mounted-otherwise"],
)
def test_station_errors_are_recorded_with_their_reason_and_touch_no_trim(
    tmp_path: Path, db: Path, bench_body: str, reason: str,
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    bench = _bench_file(tmp_path, "faulty", bench_body)
    code, doc = _run(["calibrate", "SN123", "--bench", str(bench), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 3
    assert doc["verdict"] == "error" and reason in doc["reason"]
    assert doc["trims"] is None and doc["after"] is None
    assert doc["recording"] is not None and Path(doc["recording"]).exists()
    with Store(db) as store:
        (run,) = store.history("SN123")
    assert run.verdict is not None and run.verdict.value == "error"
    assert run.bench == "faulty" and run.station_id == 7


def test_a_bad_recipe_exits_2_before_anything_is_recorded(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _recipe_variant(tmp_path, "broken", sensor_range_g=3)
    code, doc = _run(["calibrate", "SN123", "--recipe", str(recipe), "--db", str(db), "--json"],
                     monkeypatch, capsys)
    assert code == 2 and doc is None
    assert "motion.sensor_range_g" in LAST_STDERR[0]
    assert not db.exists()


class _Interrupting:
    """An operator who presses Ctrl-C as the second sweep round starts."""

    def __init__(self) -> None:
        self.sweeps = 0

    def step(self, step: Step, detail: str) -> None:
        if step is Step.SWEEP:
            self.sweeps += 1
            if self.sweeps == 2:
                raise KeyboardInterrupt

    def progress(self, done: int, total: int) -> None:
        """Nothing to show."""


@pytest.fixture
def drive_states_at_close(monkeypatch: pytest.MonkeyPatch) -> Iterator[list[DriveState]]:
    """The simulated drive's power state at the moment its bench shuts down."""
    states: list[DriveState] = []

    class WatchedBench(SimBench):
        def close(self) -> None:
            states.append(decode_statusword(self.drive.statusword()))
            super().close()

    monkeypatch.setattr(simulator, "SimBench", WatchedBench)
    yield states


def test_ctrl_c_mid_sweep_is_recorded_as_aborted_with_the_drive_disabled(
    db: Path, drive_states_at_close: list[DriveState]
) -> None:
    station = Station(db, benches.SIM_SPEC, "tester")
    result = calibrate(station, "SN123", observer=_Interrupting())
    run = result.run
    assert run.verdict is not None and run.verdict.value == "aborted"
    assert run.before is not None and run.trims_stored is False
    assert run.recording is not None and Path(run.recording).exists()
    assert drive_states_at_close[0] is not DriveState.OPERATION_ENABLED
    with Store(db) as store:
        assert store.history("SN123")[0].verdict == run.verdict


def test_recalibrate_needs_a_record_or_force(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, doc = _run(["recalibrate", "SN123", "--reason", "field return", "--db", str(db),
                      "--json"], monkeypatch, capsys)
    assert code == 2 and doc is None
    assert "--force" in LAST_STDERR[0]


def test_recalibrate_shows_the_drift_and_warns_past_the_recipe_limit(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _recipe_variant(tmp_path, "watchful", max_drift_offset_mA=4.0)
    plain = _bench_file(tmp_path, "plain", "[sim]\neffects = []\n")
    # The same motor, but its airgap flux is no longer sinusoidal: the optimum moves.
    aged = _bench_file(tmp_path, "aged", '[sim]\neffects = ["flux_harmonics"]\n')
    code, first = _run(["calibrate", "SN123", "--recipe", str(recipe), "--bench", str(plain),
                        "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0, first["reason"]
    recipe.unlink()  # field service has only the database's copy of this recipe
    code, again = _run(["recalibrate", "SN123", "--reason", "noisy in the field",
                        "--bench", str(aged), "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 0, again["reason"]
    assert (again["recipe"], again["recipe_sha256"]) == (first["recipe"], first["recipe_sha256"])
    assert again["kind"] == "recalibrate" and again["service_reason"] == "noisy in the field"
    assert again["previous_trims"] == first["trims"]
    assert again["previous_run_id"] == first["run_id"]
    expected = {k: again["trims"][k] - first["trims"][k] for k in TRIM_KEYS}
    assert again["drift"] == expected
    assert abs(expected["offset_a_mA"]) > 4.0
    assert any("offset A drifted" in w for w in again["warnings"])


def test_query_filters_runs_and_writes_csv(
    tmp_path: Path, db: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    # A sensor far too noisy for its self-check: each run ends ERROR within moments.
    wrong = _bench_file(tmp_path, "wrong", "[sim]\nnoise_ug = 20000\n")
    _run(["calibrate", "SN123", "--bench", str(wrong), "--db", str(db), "--json"],
         monkeypatch, capsys)
    _run(["calibrate", "SN124", "--bench", str(wrong), "--db", str(db), "--json"],
         monkeypatch, capsys)
    code, runs = _run(["query", "--verdict", "error", "--serial", "SN124", "--db", str(db),
                       "--json"], monkeypatch, capsys)
    assert code == 0 and [r["serial"] for r in runs] == ["SN124"]
    code, runs = _run(["query", "--station", "7", "--db", str(db), "--json"], monkeypatch, capsys)
    assert [r["serial"] for r in runs] == ["SN123", "SN124"]
    code, runs = _run(["query", "--since", "2999-01-01", "--db", str(db), "--json"],
                      monkeypatch, capsys)
    assert runs == []
    monkeypatch.setattr(sys, "argv", ["station", "query", "--format", "csv", "--db", str(db)])
    with pytest.raises(SystemExit):
        main()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("run_id,serial,kind,started_at")
    assert len(lines) == 3


def test_a_recording_is_never_overwritten_by_a_run_of_the_same_number(
    station_home: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    # A database begun again (a new file) numbers its runs from 1 in the same folder.
    older = station_home / "recordings" / "SN123" / "SN123-run000001.blf"
    older.parent.mkdir(parents=True)
    older.write_bytes(b"a recording of an earlier database")
    code, doc = _run(["calibrate", "SN123", "--json"], monkeypatch, capsys)
    assert code == 0 and doc["run_id"] == 1, LAST_STDERR[0]
    assert Path(doc["recording"]).name == f"SN123-run000001-{doc['run_uuid']}.blf"
    assert older.read_bytes() == b"a recording of an earlier database"


def test_verify_of_a_unit_never_calibrated_says_no_record_and_what_to_do(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    code, doc = _run(["verify", "SN777", "--db", str(db), "--json"], monkeypatch, capsys)
    assert code == 1 and doc["match"] is False and doc["recorded"] is False
    assert doc["recorded_trims"] is None
    monkeypatch.setattr(sys, "argv", ["station", "verify", "SN777", "--db", str(db)])
    with pytest.raises(SystemExit) as stop:
        main()
    shown = " ".join(capsys.readouterr().out.split())
    assert stop.value.code == 1 and "NO RECORD" in shown and "MISMATCH" not in shown
    assert "station calibrate SN777" in shown


def test_station_version_prints_the_software_version(
    monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    monkeypatch.setattr(sys, "argv", ["station", "--version"])
    with pytest.raises(SystemExit) as stop:
        main()
    assert stop.value.code in (0, None)
    assert capsys.readouterr().out.strip() == __version__
