"""The diagnosis report page (station.diagnosis.report) a motion engineer reads.

One recording of the simulated bench (a disk unit with cogging, a drawn
characterization schedule, made in process) is diagnosed once per module;
the page must then show what the diagnosis concluded and the evidence behind
it. What the page says when a significant residual is left is checked on the
same diagnosis with its verdict on the residual swapped: the page's wording
is under test there, not the physics (the acceptance test judges that).
"""

from __future__ import annotations

import html
import re
from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import pytest

from station.analysis.reader import read_recording
from station.core import Effect
from station.diagnosis.diagnose import diagnose
from station.diagnosis.report import (
    MAX_HARMONIC_ROWS,
    _chi2,
    _flatten,
    _nominal_section,
    render_html,
    write_report,
)
from station.diagnosis.results import Diagnosis, LocatedKind, LoneHold, Unexplained
from station.htmlpage import num as _num
from station.sim.concealed import Case, TrialClass, plan_trial, record_trial
from station.views import diagnosis_view
from tests.browser import overflow_px

SOURCE = "recordings/SN900024-characterize.blf"
CASE = Case(TrialClass(frozenset({Effect.DETENT_TORQUE})), 24)
"""A development seed: a disk unit whose cogging the diagnosis names."""


@pytest.fixture(scope="module")
def diagnosis(tmp_path_factory: pytest.TempPathFactory) -> Diagnosis:
    root = tmp_path_factory.mktemp("report-recording")
    (root / "rec").mkdir()
    (root / "truth").mkdir()
    plan = plan_trial(CASE)
    out = record_trial(plan, root / "rec" / "unit.blf", root / "truth" / "unit.json")
    result = diagnose(read_recording(out))
    assert Effect.DETENT_TORQUE in {e.effect for e in result.effects}, result.to_dict()["effects"]
    return result


@pytest.fixture(scope="module")
def report_path(diagnosis: Diagnosis, tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("report") / "SN1.html"
    assert write_report(diagnosis, path, source=SOURCE) == path
    return path


@pytest.fixture(scope="module")
def page(report_path: Path) -> str:
    """The page as first written (read once: one test writes the file again)."""
    assert report_path.is_file()
    return report_path.read_text(encoding="utf-8")


def _text(page: str) -> str:
    """The page without its figures and tags: what a reader reads."""
    bare = re.sub(r"<[^>]+>", " ", re.sub(r"<svg.*?</svg>", " ", page, flags=re.S))
    return " ".join(html.unescape(bare).split())


def test_report_is_one_self_contained_html_page(page: str) -> None:
    assert page.startswith("<!DOCTYPE html>")
    assert page.rstrip().endswith("</html>")
    for external in ("<script", "<link", "<img", "src="):
        assert external not in page


def test_report_names_the_drive_the_recording_and_the_verdict(
    diagnosis: Diagnosis, page: str
) -> None:
    fit = diagnosis.to_dict()["fit"]
    text = _text(page)
    assert diagnosis.observations.metadata.serial in text
    assert SOURCE in text
    assert "Mismatch" in text
    assert f"{fit['before']:.3g}" in text
    assert f"{fit['after']:.3g}" in text
    assert f"{fit['after_chi2']:.1f}" in text


def test_report_shows_each_named_effect_with_its_evidence_and_parameters(
    diagnosis: Diagnosis, page: str
) -> None:
    text = _text(page)
    assert "evidence: located cells it explains" in text
    for effect in diagnosis.effects:
        assert effect.effect.value in text
        for key, order, before, after in effect.explains:
            assert f"{key.label()}, order {order}" in text
            assert f"{_chi2(before)} → {_chi2(after)}" in text  # as the page rounds χ²
    detent = next(e for e in diagnosis.effects if e.effect is Effect.DETENT_TORQUE)
    assert detent.explains, "cogging must explain located cells for the page to show them"
    assert "± " in text  # parameters carry their σ


def test_report_says_when_what_is_left_is_noise(diagnosis: Diagnosis, page: str) -> None:
    text = _text(page)
    if diagnosis.unexplained.significant:
        assert "A significant residual is left" in text
    else:
        assert "is noise: χ²" in text
        assert "A significant residual is left" not in text


def test_report_says_plainly_when_a_significant_residual_is_left(diagnosis: Diagnosis) -> None:
    left = Unexplained(chi2=9876.0, values=1200, significant=True)
    text = _text(render_html(replace(diagnosis, unexplained=left), source=SOURCE))
    assert "A significant residual is left" in text
    assert "9876.0 for 1200 values" in text
    assert "No id describes what remains" in text


def test_report_names_the_one_hold_that_carries_what_is_left_instead_of_calling_it_noise(
    diagnosis: Diagnosis,
) -> None:
    condition = diagnosis.observations.conditions[0]
    lone = LoneHold(condition, 7.144, 7.424, 1793.9, 17)
    left = Unexplained(chi2=2719.5, values=970, significant=False, lone=lone)
    text = _text(render_html(replace(diagnosis, unexplained=left), source=SOURCE))
    assert "noise but for one hold: χ² 2719.5 for 970 values, 1793.9 of it" in text
    assert f"{condition.label()}, 7.14–7.42 s" in text
    assert "is noise: χ²" not in text
    assert "A significant residual is left" not in text


def test_report_shows_measured_nominal_and_extended_harmonics(
    diagnosis: Diagnosis, page: str
) -> None:
    assert page.count("<svg") >= 3
    for legend in ("measured, ±σ", "nominal model", "extended model"):
        assert legend in page
    for order in range(1, diagnosis.observations.orders + 1):
        assert f"order {order}" in page
    for key in diagnosis.observations.conditions:
        assert key.label() in page


def test_report_maps_where_the_nominal_model_fails_and_the_trims_drift(page: str) -> None:
    assert "Where the nominal model fails" in page
    assert "χ² per degree of freedom" in page
    assert "optimal offset A (mA)" in page
    assert "optimal gain split (1/10000)" in page


def test_report_lists_holds_used_and_skipped(diagnosis: Diagnosis, page: str) -> None:
    text = _text(page)
    obs = diagnosis.observations
    assert f"{obs.count} segments used, {obs.model_settled} of them" in text
    for skipped in obs.skipped:
        assert skipped.reason in text


def test_report_tables_located_entries_naming_rounds_and_thresholds(
    diagnosis: Diagnosis, page: str
) -> None:
    text = _text(page)
    located = [loc for loc in diagnosis.located
               if loc.kind in (LocatedKind.HARMONIC, LocatedKind.UNEXPLAINED)]
    assert f"{len(located)} harmonic entries located" in text
    assert page.count("<td>nominal residual</td>") + page.count("<td>unexplained</td>") == min(
        len(located), MAX_HARMONIC_ROWS)
    for rnd in diagnosis.rounds:
        for test in rnd.tried:
            assert test.larger.label in text
    for threshold in ("SIGNIFICANT_CONFIDENCE", "MAX_EFFECTS", "RIVAL_Z", "UNEXPLAINED_RATIO"):
        assert threshold in text


def test_rewriting_a_report_replaces_it_whole_and_escapes_text(
    diagnosis: Diagnosis, report_path: Path, page: str
) -> None:
    assert SOURCE in page
    write_report(diagnosis, report_path, source="<b>second</b> & more.mf4")
    again = report_path.read_text(encoding="utf-8")
    assert SOURCE not in again
    assert "&lt;b&gt;second&lt;/b&gt; &amp; more.mf4" in again
    assert "<b>second</b>" not in again
    assert [p.name for p in report_path.parent.iterdir()] == [report_path.name]  # no temporary


def test_report_leaves_no_figure_open(page: str) -> None:
    assert page
    assert plt.get_fignums() == []


def test_report_shows_the_nominal_model_as_physical_quantities_with_sigma(
    diagnosis: Diagnosis, page: str,
) -> None:
    text = _text(page)
    nominal = diagnosis.to_dict()["nominal"]
    assert "rotor natural frequency at rated current" in text
    assert f"{_num(nominal['rotor_natural_hz_at_rated_current'])} ± " in text
    assert "load_angles[" not in text  # no dotted keys: a table per condition instead
    for key in diagnosis.observations.conditions:
        assert f"<td>{key.label()}</td>" in page


def _nominal_doc(friction_percent: float, load_angle: float) -> dict[str, object]:
    condition = {"amplitude_mA": 1000, "electrical_hz": 20.0, "direction": 1,
                 "load_angle_rad": load_angle, "load_angle_sigma_rad": 0.001,
                 "friction_percent_of_rated_holding_torque": friction_percent}
    return {"nominal": {"chain": "rigid", "rotor_natural_hz_at_rated_current": 120.0,
                        "rotor_natural_hz_sigma": 0.1, "rotor_damping_ratio": 0.07,
                        "rotor_damping_ratio_sigma": 0.001, "chi2_per_dof": 1.1,
                        "load_angles": [condition], "states": {}}}


def test_report_flags_fitted_values_no_motor_on_the_fixture_can_have() -> None:
    plausible = _nominal_section(_nominal_doc(3.0, 0.05))
    assert "implausible" not in plausible
    flagged = _nominal_section(_nominal_doc(52.0, 0.88))
    assert flagged.count("<tr class='implausible'>") == 1  # the one condition's row
    assert "more than 25 % of the holding torque lost to friction" in flagged
    assert "beyond 45°, near pull-out (90°)" in flagged
    # Effect parameters are flagged by what their keys say they are, σ beside the value.
    rows = dict(_flatten({"coulomb_forward_percent_of_rated_holding_torque": 37.0,
                          "coulomb_forward_sigma_percent": 0.5}))
    assert rows == {"coulomb_forward_percent_of_rated_holding_torque":
                    "37.00 ± 0.50  ⚠ implausible: more than 25 % of the holding torque lost "
                    "to friction"}


def test_the_headline_agrees_with_what_is_located(diagnosis: Diagnosis) -> None:
    calm = replace(diagnosis, effects=(), findings=(),
                   unexplained=Unexplained(chi2=900.0, values=1000, significant=False))
    doc = calm.to_dict()
    assert not doc["mismatch"] and doc["located"], "the case must locate disagreements"
    text = _text(render_html(calm, source=SOURCE))
    assert "No mismatch that matters" in text
    assert f"{len(doc['located'])} disagreement(s) of the paper's model are located" in text
    assert "No mismatch: the paper's model explains" not in text
    doc["serial"], doc["recording"] = "SN1", SOURCE
    doc["conditions"] = [c.label() for c in calm.observations.conditions]
    head = diagnosis_view(doc).renderables[0]
    assert str(head).startswith("SN1: no mismatch that matters")


def test_the_page_reads_on_a_desktop_and_on_a_phone_without_sideways_scrolling(
    report_path: Path, chromium: str, tmp_path: Path,
) -> None:
    page = tmp_path / "diagnosis.html"
    page.write_text(report_path.read_text(encoding="utf-8"), encoding="utf-8")
    for width in (1400, 400):
        assert overflow_px(chromium, page, width) == 0, width
