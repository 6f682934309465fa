"""Every injected fault of the simulated bench, end to end through ``station calibrate``.

Whatever breaks, the same promises hold (``_assert_safe``): the run is in the
database with a verdict and a reason naming the device; the drive is left
disabled; its EEPROM holds exactly the trims the database says were last
stored, and its RAM the same unless the drive could no longer be reached
(the run then says so); and a PASS is never built on data a fault spoiled.
"""

from __future__ import annotations

import logging
import re
from dataclasses import dataclass, field, replace
from pathlib import Path

import pytest

from station.bench_names import BenchFileError
from station.benches import SIM_MODBUS_SPEC, SIM_SPEC, BenchSpec, parse_bench
from station.core import NOMINAL_TRIMS
from station.runs import Run, Verdict
from station.service import Station, calibrate
from station.sim.bench import SimBench, SimBenchConfig, TrimsLeft
from station.simsettings import Fault, FaultKind, SimSettings
from station.steps import Step
from station.store import Store

SERIAL = "SN123"


@dataclass(frozen=True)
class Case:
    fault: Fault
    verdict: Verdict
    # What the reason must say, from its start (a regular expression): the device and the
    # failure. A run that passes must say that every limit was met, nothing else.
    reason: str = r"all limits met\Z"
    warning: str = ""  # what a run that survives must say about it


CANOPEN_CASES = {
    # Retried (2 retries), so two lost requests cost time, not the unit.
    "sdo-timeouts-retried": Case(Fault(FaultKind.SDO_TIMEOUT, 0.0, 2), Verdict.PASS),
    "sdo-timeouts-beyond-retries": Case(Fault(FaultKind.SDO_TIMEOUT, 1.5, 5), Verdict.ERROR,
                                        r"drive: SDO 0x2100:01: no answer to 3 attempts"),
    "drive-silent": Case(Fault(FaultKind.DRIVE_SILENT, 1.5), Verdict.ERROR,
                         r"drive: silent: last heartbeat"),
    "sensor-silent": Case(Fault(FaultKind.SENSOR_SILENT, 1.5), Verdict.ERROR,
                          r"sensor: silent: last heartbeat"),
    # Holes the analysis sees and leaves out: the unit is still measured.
    "sensor-frames-lost-burst": Case(Fault(FaultKind.SENSOR_FRAMES_LOST, 1.5, 8), Verdict.PASS),
    "sensor-frames-lost-for-good": Case(Fault(FaultKind.SENSOR_FRAMES_LOST, 1.5, 25),
                                        Verdict.ERROR, r"sensor: no frame 0x190 for \d+ "),
    "error-frames": Case(Fault(FaultKind.ERROR_FRAMES, 1.5, 40), Verdict.PASS,
                         warning="40 CAN error frames"),
    "bus-off": Case(Fault(FaultKind.BUS_OFF, 1.5), Verdict.ERROR,
                    r"CAN virtual:station-sim-\w+: bus-off after 1 error frames"),
    "eeprom-refuses-to-store": Case(Fault(FaultKind.EEPROM_FAILURE, 0.0), Verdict.ERROR,
                                    r"drive: SDO 0x1010:01 aborted with 0x08000020 \(data cannot"),
    "power-cycle": Case(Fault(FaultKind.POWER_CYCLE, 1.5), Verdict.ERROR,
                        r"drive: sent a boot-up frame mid-run"),
    # At the rail on every axis, the hold's gravity check is what refuses it.
    "sensor-saturated": Case(Fault(FaultKind.SENSOR_SATURATED, 1.5), Verdict.ERROR,
                             r"sensor: axis z reads \+\d+\.\d\d m/s² on average, not gravity"),
    "sensor-unplugged": Case(Fault(FaultKind.SENSOR_UNPLUGGED, 1.5), Verdict.ERROR,
                             r"sensor: axis z reads [+-]\d+\.\d\d m/s² on average, not gravity"),
}

MODBUS_CASES = {
    "sdo-timeouts-retried": Case(Fault(FaultKind.SDO_TIMEOUT, 1.5, 2), Verdict.PASS),
    "drive-silent": Case(Fault(FaultKind.DRIVE_SILENT, 1.5), Verdict.ERROR,
                         r"drive: Modbus TCP 127\.0\.0\.1:\d+ unit 1: function 0x03 at register "
                         r"0x0001 \(timeout [\d.]+ s\): no answer to 3 attempts"),
    "eeprom-refuses-to-store": Case(Fault(FaultKind.EEPROM_FAILURE, 0.0), Verdict.ERROR,
                                    r"drive: Modbus .*exception 0x04"),
    "power-cycle": Case(Fault(FaultKind.POWER_CYCLE, 1.5), Verdict.ERROR,
                        r"drive: left operation enabled by itself"),
}


class _Watched(SimBench):
    """A simulated bench that says when the station closed it."""

    def __init__(self, config: SimBenchConfig, closed: list[SimBench]) -> None:
        super().__init__(config)
        self._seen_closed = closed

    def close(self) -> None:
        super().close()
        if self not in self._seen_closed:
            self._seen_closed.append(self)


@dataclass
class Benches:
    """Every simulated bench a calibration opened, as it was when the station closed it:
    the bench's simulator is injected through its spec, as any caller may."""

    closed: list[SimBench] = field(default_factory=list)

    def open(self, config: SimBenchConfig) -> SimBench:
        return _Watched(config, self.closed)

    def spec(self, base: BenchSpec, *faults: Fault) -> BenchSpec:
        return replace(base, sim=SimSettings(faults=faults), simulator=self.open)


@pytest.fixture
def benches() -> Benches:
    return Benches()


def _assert_safe(run: Run, bench: SimBench, db: Path) -> None:
    """The promises every run keeps, whatever went wrong."""
    assert run.verdict is not None and run.reason
    assert run.run_id is not None and run.finished_at is not None
    with Store(db) as store:
        recorded = store.get_run(run.run_id)
        last = store.last_stored(run.serial)
    assert recorded.verdict is run.verdict and recorded.reason == run.reason
    end = bench.at_close
    assert end is not None
    assert not end.enabled, f"drive left {end.state.value}"
    left = end.trims_against(last.trims_after if last is not None else None)
    assert left is not TrimsLeft.EEPROM_DIFFERS, "the EEPROM differs from the last stored"
    if left is TrimsLeft.RAM_DIFFERS:
        # Only a drive the station could no longer reach keeps trims under test in RAM,
        # and the run says so.
        assert any("could not restore" in w for w in run.warnings), run.warnings
    if run.verdict is Verdict.PASS:
        assert run.trims_stored and run.trims_after == end.stored_trims


@pytest.mark.parametrize("name", list(CANOPEN_CASES))
def test_a_canopen_bench_fault_ends_as_expected_with_the_drive_safe(
    name: str, tmp_path: Path, benches: Benches, caplog: pytest.LogCaptureFixture,
) -> None:
    case = CANOPEN_CASES[name]
    db = tmp_path / "station.db"
    with caplog.at_level(logging.WARNING):
        run = calibrate(Station(db, benches.spec(SIM_SPEC, case.fault), "tester"), SERIAL).run
    (bench,) = benches.closed
    assert run.verdict is case.verdict, run.reason
    assert re.match(case.reason, run.reason or ""), run.reason
    assert bench.faults.effects, "the fault never took effect: the case tests nothing"
    _assert_safe(run, bench, db)
    if case.warning:
        assert any(case.warning in w for w in run.warnings), run.warnings
    if case.fault.kind is FaultKind.SDO_TIMEOUT and case.verdict is Verdict.PASS:
        assert "sending it again (retry 1 of 2)" in caplog.text


@pytest.mark.parametrize("name", list(MODBUS_CASES))
def test_a_modbus_bench_fault_ends_as_expected_with_the_drive_safe(
    name: str, tmp_path: Path, benches: Benches,
) -> None:
    case = MODBUS_CASES[name]
    db = tmp_path / "station.db"
    run = calibrate(Station(db, benches.spec(SIM_MODBUS_SPEC, case.fault), "tester"), SERIAL).run
    (bench,) = benches.closed
    assert run.verdict is case.verdict, run.reason
    assert re.match(case.reason, run.reason or ""), run.reason
    assert bench.faults.effects
    _assert_safe(run, bench, db)


def test_a_store_refused_after_the_trims_were_stored_keeps_the_record_truthful(
    tmp_path: Path, benches: Benches,
) -> None:
    """The EEPROM breaks between the trims' store and the calibration record's: the new
    trims stay stored (the rollback's store is refused too) and the record says so."""
    db = tmp_path / "station.db"
    # The same unit, calibrated apart, times its own verification: the last 0.5 s of its
    # motion (spin-up, settle and the first hold), longer where it went on measuring.
    probe = calibrate(Station(tmp_path / "probe.db", SIM_SPEC, "tester"), SERIAL).run
    assert probe.verdict is Verdict.PASS and probe.motion_s is not None
    # Armed during the verification: after the trims' store, before the record's.
    late = Fault(FaultKind.EEPROM_FAILURE, probe.motion_s - 0.3)
    run = calibrate(Station(db, benches.spec(SIM_SPEC, late), "tester"), SERIAL).run
    bench = benches.closed[-1]
    assert run.verdict is Verdict.ERROR and "0x1010:01" in (run.reason or "")
    assert run.trims_stored and run.trims_after is not None
    assert any("could not restore its previous trims" in w for w in run.warnings)
    _assert_safe(run, bench, db)
    assert bench.at_close is not None and bench.at_close.stored_trims == run.trims_after


class _StopAt:
    """An operator who presses Ctrl-C when the station reaches ``step``."""

    def __init__(self, step: Step) -> None:
        self.at = step

    def step(self, step: Step, detail: str) -> None:
        if step is self.at:
            raise KeyboardInterrupt

    def progress(self, done: int, total: int) -> None:
        """Nothing to show."""


def test_ctrl_c_after_the_trims_were_stored_rolls_the_eeprom_back(
    tmp_path: Path, benches: Benches,
) -> None:
    db = tmp_path / "station.db"
    run = calibrate(Station(db, benches.spec(SIM_SPEC), "tester"), SERIAL,
                    observer=_StopAt(Step.VERIFY)).run
    (bench,) = benches.closed
    assert run.verdict is Verdict.ABORTED
    assert not run.trims_stored and run.trims_after is None
    assert any("rolled back" in w for w in run.warnings)
    _assert_safe(run, bench, db)
    assert bench.at_close is not None and bench.at_close.stored_trims == NOMINAL_TRIMS


def test_faults_in_a_bench_file_are_read_strictly() -> None:
    spec = parse_bench(
        '[sim]\n[[sim.faults]]\nkind = "power_cycle"\nat_s = 2.5\n'
        '[[sim.faults]]\nkind = "sensor_frames_lost"\nat_s = 1\ncount = 12\n',
        source="faulty.toml",
    )
    assert spec.sim is not None
    assert spec.sim.faults == (Fault(FaultKind.POWER_CYCLE, 2.5),
                               Fault(FaultKind.SENSOR_FRAMES_LOST, 1.0, 12))
    with pytest.raises(BenchFileError) as refused:
        parse_bench('[sim]\n[[sim.faults]]\nkind = "gremlins"\n[[sim.faults]]\n'
                    'kind = "power_cycle"\ncount = 3\nwhen = 1\n', source="bad.toml")
    message = str(refused.value)
    assert "sim.faults[0].kind: must be one of" in message
    assert "sim.faults[1].count: means nothing for power_cycle" in message
    assert "sim.faults[1].when: unknown key" in message


def test_a_unit_failed_before_its_trims_are_written_keeps_its_own_in_ram_too(
    tmp_path: Path, benches: Benches,
) -> None:
    default = (Path(__file__).parents[2] / "recipes" / "default.toml").read_text("utf-8")
    narrow = tmp_path / "narrow.toml"
    narrow.write_text(default.replace('name = "default"', 'name = "narrow"').replace(
        "offset_bound_mA = ", "offset_bound_mA = 20.0 #"), encoding="utf-8")
    db = tmp_path / "station.db"
    run = calibrate(Station(db, benches.spec(SIM_SPEC), "tester"), SERIAL, str(narrow)).run
    (bench,) = benches.closed
    assert run.verdict is Verdict.FAIL and not run.trims_stored
    _assert_safe(run, bench, db)
    assert bench.at_close is not None and bench.at_close.ram_trims == NOMINAL_TRIMS
