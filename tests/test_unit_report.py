"""A unit's calibration report: the paper's figures for that unit, and what to do next.

Every calibration leaves a page beside its recording; ``station report`` draws
any run's page again; ``analyze --report`` draws a recording alone. The page is
checked as a person would: its numbers are the record's, and chromium renders
it without sideways scrolling on a desktop and on a phone.
"""

from __future__ import annotations

import re
from dataclasses import replace
from pathlib import Path

import pytest
from PIL import Image

from station.errors import InputError
from station.htmlpage import num
from station.reports import REPORT_SUFFIX, write_run_report
from station.store import Store
from tests.browser import overflow_px, screenshot
from tests.cli import Outcome, run_cli

SWEEP_FIGURES = 3  # |H1|² against offset A and B, |H2|² against the gain split
BEFORE_AFTER_FIGURES = 2  # harmonics, time-domain ripple


@pytest.fixture
def db(tmp_path: Path) -> Path:
    return tmp_path / "results" / "station.db"


def _narrow_recipe(folder: Path) -> Path:
    """The default recipe with offset bounds no drawn unit meets: a unit that fails."""
    text = (Path(__file__).parents[1] / "recipes" / "default.toml").read_text(encoding="utf-8")
    text = text.replace('name = "default"', 'name = "narrow"')
    text, count = re.subn(r"(?m)^offset_bound_mA = .*$", "offset_bound_mA = 20.0", text)
    assert count == 1
    path = folder / "narrow.toml"
    path.write_text(text, encoding="utf-8")
    return path


def _calibrate(args: list[str], monkeypatch: pytest.MonkeyPatch,
               capsys: pytest.CaptureFixture[str]) -> Outcome:
    return run_cli(["calibrate", *args], monkeypatch, capsys)


def test_a_calibration_leaves_the_paper_figures_and_its_record_beside_its_recording(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    done = _calibrate(["SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert done.code == 0
    doc = done.doc
    recording = Path(doc["recording"])
    page = Path(doc["report"])
    assert page == recording.with_name(recording.stem + REPORT_SUFFIX) and page.is_file()
    html = page.read_text(encoding="utf-8")
    # Self-contained: no script, no external resource, figures as inline SVG.
    assert "<script" not in html and "<link" not in html and " src=" not in html
    assert html.count("<svg") == SWEEP_FIGURES + BEFORE_AFTER_FIGURES
    assert "v-pass" in html and "all limits met" in html
    # The trims and their σ are the record's, to the digits the page shows.
    for key in ("offset_a_mA", "offset_b_mA", "gain_a", "gain_b"):
        shown = f"{num(doc['trims_estimated'][key])} ± {num(doc['uncertainty'][key], 2)}"
        assert shown in html, key
    for check in doc["limits"]:
        assert f"<td>{check['name']}</td>" in html
    assert "paper&#x27;s parabola" in html or "paper's parabola" in html
    assert str(recording) in html
    assert html.count("<td class='num'>") > 40  # every hold's row


def test_station_report_draws_a_run_by_id_or_a_unit_s_newest_with_its_drift(
    db: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert _calibrate(["SN123", "--db", str(db), "--no-report", "--json"], monkeypatch,
                      capsys).code == 0
    again = run_cli(["recalibrate", "SN123", "--reason", "field return", "--db", str(db),
                     "--no-report", "--json"], monkeypatch, capsys)
    assert again.code == 0 and "report" not in again.doc
    first = run_cli(["report", "1", "--db", str(db), "--out", str(tmp_path / "one.html"),
                     "--json"], monkeypatch, capsys)
    assert first.code == 0 and first.doc["run_id"] == 1
    assert first.doc["report"] == str(tmp_path / "one.html")
    newest = run_cli(["report", "SN123", "--db", str(db), "--json"], monkeypatch, capsys)
    assert newest.code == 0 and newest.doc["run_id"] == 2 and newest.doc["notes"] == []
    html = Path(newest.doc["report"]).read_text(encoding="utf-8")
    # The unit's history: both runs, the change since the first, and the drift figure.
    assert "change since the last stored" in html and "field return" in html
    assert html.count("<svg") == SWEEP_FIGURES + BEFORE_AFTER_FIGURES + 1
    # People get the path alone on stdout, whole.
    shown = run_cli(["report", "2", "--db", str(db)], monkeypatch, capsys)
    assert shown.code == 0 and shown.stdout.strip() == newest.doc["report"]


def test_a_failed_unit_says_what_to_do_next_on_screen_in_json_and_in_its_report(
    db: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _narrow_recipe(tmp_path)
    monkeypatch.setenv("COLUMNS", "80")
    done = _calibrate(["SN5038", "--recipe", str(recipe), "--db", str(db)], monkeypatch, capsys)
    assert done.code == 1
    # The README's steps numbered, with the time the run has taken.
    assert re.search(r"step 1 of 9 +\d+\.\d s +connect", done.err)
    assert re.search(r"step 7 of 9 +\d+\.\d s +verify", done.err) is None  # never trimmed
    assert re.search(r"step 5 of 9 +\d+\.\d s +estimate", done.err)
    # The whole reason and the next step, wrapped inside the banner, never cut.
    banner = " ".join(line.strip("│╭╮╰╯─ ") for line in done.stdout.splitlines())
    banner = " ".join(banner.split())
    assert "failed offset_a_mA = -128 mA (limit -20); offset_b_mA = -119 mA (limit -20)" in banner
    assert ("next: not trimmed; the unit keeps its trims; the drive needs more correction than "
            "the recipe allows") in banner
    assert "`station characterize SN5038`" in banner
    assert all(len(line) <= 80 for line in done.stdout.splitlines() if line.startswith("│"))
    # Paths whole, on their own line, to be copied.
    recording = next(line for line in done.stdout.splitlines() if line.startswith("recording: "))
    report = Path(recording.removeprefix("recording: ").replace(".blf", REPORT_SUFFIX))
    assert Path(recording.removeprefix("recording: ")).is_file() and report.is_file()
    html = report.read_text(encoding="utf-8")
    assert "v-fail" in html and "<b>Next:</b> not trimmed; the unit keeps its trims" in html
    assert "class='failed'" in html  # the limits that failed stand out in the table
    assert "no hold at stored trims (nothing was stored)" in html
    listed = run_cli(["history", "SN5038", "--db", str(db), "--json"], monkeypatch, capsys)
    assert listed.doc[0]["next_step"].startswith("not trimmed; the unit keeps its trims")


def test_a_report_names_what_it_cannot_show_and_refuses_what_does_not_exist(
    db: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    for key, said in (("9", "no run 9 in database"), ("SN999", "no runs of SN999 are recorded"),
                      ("SN01", "serial 'SN01' is malformed")):
        refused = run_cli(["report", key, "--db", str(db)], monkeypatch, capsys)
        assert refused.code == 2 and said in refused.stderr, key
    assert _calibrate(["SN123", "--db", str(db), "--no-report", "--json"], monkeypatch,
                      capsys).code == 0
    with Store(db) as store:
        (run,) = store.history("SN123")
    assert run.recording is not None
    recording = Path(run.recording)
    # A run that never moved has nothing to put a page beside, but can be drawn elsewhere.
    unmoved = replace(run, recording=None, recording_sha256=None)
    with pytest.raises(InputError, match="has no recording to put a report beside"):
        write_run_report(unmoved, [run])
    drawn = write_run_report(unmoved, [run], tmp_path / "unmoved.html")
    assert drawn.notes == ("run 1 has no recording: it ended before the motor moved "
                           "(all limits met)",)
    assert "<svg" not in drawn.path.read_text(encoding="utf-8")
    # A recording changed since the run is named as such, and what cannot be read too.
    recording.write_bytes(recording.read_bytes()[:4096])
    changed = write_run_report(run, [run], tmp_path / "changed.html")
    assert any("is not the file run 1 recorded (its sha256 differs)" in n for n in changed.notes)
    assert any(n.startswith("the recording could not be analysed: ") for n in changed.notes)
    recording.unlink()
    gone = run_cli(["report", "1", "--db", str(db), "--json"], monkeypatch, capsys)
    assert gone.code == 0
    assert gone.doc["notes"] == [f"the recording {recording} is no longer there: the page "
                                 "shows the record alone"]


def test_analyze_report_draws_a_recording_alone(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    done = _calibrate(["SN123", "--db", str(db), "--no-report", "--json"], monkeypatch, capsys)
    recording = Path(done.doc["recording"])
    analysed = run_cli(["analyze", str(recording), "--report", "--json"], monkeypatch, capsys)
    assert analysed.code == 0
    html = Path(analysed.doc["report"]).read_text(encoding="utf-8")
    assert "No station record is shown" in html and "<h2>Limits</h2>" not in html
    assert html.count("<svg") == SWEEP_FIGURES + BEFORE_AFTER_FIGURES


def _colours(png: Path) -> int:
    with Image.open(png) as image:
        return len(image.convert("RGB").getcolors(maxcolors=1 << 20) or ())


def test_the_report_reads_on_a_desktop_and_on_a_phone_without_sideways_scrolling(
    db: Path, tmp_path: Path, chromium: str, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    recipe = _narrow_recipe(tmp_path)  # a FAIL page: the banner's longest text
    done = _calibrate(["SN5038", "--recipe", str(recipe), "--db", str(db), "--json"],
                      monkeypatch, capsys)
    page = Path(done.doc["report"])
    for width in (1400, 400):
        assert overflow_px(chromium, page, width) == 0, width
        shot = screenshot(chromium, page, width, tmp_path / f"report-{width}.png")
        assert _colours(shot) > 50  # text, figures and tables, not a blank or error page
    # The probe can fail: a page wider than the phone overflows it.
    wide = tmp_path / "wide.html"
    wide.write_text("<!DOCTYPE html><html><body><div style='width:900px'>x</div></body></html>",
                    encoding="utf-8")
    assert overflow_px(chromium, wide, 400) > 0


def test_a_modbus_drive_s_report_draws_its_sweeps_though_its_holds_are_short(
    db: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str],
) -> None:
    # A Modbus drive sends no angle and its holds are too short to judge their own
    # settling: the page analyses them with the run's recipe's settling, as the run did.
    done = _calibrate(["SN123", "--bench", "sim-modbus", "--db", str(db), "--json"],
                      monkeypatch, capsys)
    assert done.code == 0
    html = Path(done.doc["report"]).read_text(encoding="utf-8")
    assert html.count("<svg") == SWEEP_FIGURES + BEFORE_AFTER_FIGURES
    assert "No sweep along" not in html and "could not be analysed" not in html
    assert f"paper estimate {num(done.doc['trims_estimated']['offset_a_mA'])}" in html
