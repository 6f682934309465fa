"""The diagnosis report page (station.diagnosis.report), on a diagnosis of synthetic harmonics.

The harmonics are made by the diagnosis's own model run forward: a nominal
motor with amplifier offsets and gain errors plus a known cogging torque,
the motion solved by Newton steps on the model's equation error (each
``Model.predicted`` is one such step), then noise added. That is enough
physics for the diagnosis to name the cogging, which is what the page must
then show; the page's own correctness is judged on its content, not on the
physics.
"""

from __future__ import annotations

import math
import re
from dataclasses import replace
from pathlib import Path

import matplotlib.pyplot as plt
import numpy as np
import pytest

from station.analysis.segments import Segment
from station.core import Effect, Trims
from station.diagnosis.diagnose import Diagnosis, LocatedKind, diagnose_observations
from station.diagnosis.model import ChainKind, Model, ModelSpec
from station.diagnosis.observations import DIAGNOSIS_ORDERS, ConditionKey, Observations
from station.diagnosis.report import MAX_HARMONIC_ROWS, write_report
from tests.metadata import icd_metadata

META = icd_metadata(serial="SN1", sensor_lsb_mps2=0.0024, sensor_radius_m=0.04)
CONDITIONS = (
    ConditionKey(600, 20.0),
    ConditionKey(600, -20.0),
    ConditionKey(1000, 20.0),
    ConditionKey(1000, -20.0),
    ConditionKey(1000, 35.0),
    ConditionKey(600, -35.0),
)
# Trim steps of a characterization: as found, offset A, offset B, gain split.
TRIM_STEPS = (
    (0.0, 0.0, 10000.0, 10000.0),
    (40.0, 0.0, 10000.0, 10000.0),
    (0.0, 40.0, 10000.0, 10000.0),
    (0.0, 0.0, 10400.0, 9600.0),
)
NOISE_MPS2 = 0.01
SOURCE = "recordings/SN1-characterize.mf4"


def _segment(index: int, key: ConditionKey, trims: tuple[float, ...]) -> Segment:
    per_sample = key.electrical_hz * 4 * META.microsteps_per_fullstep * META.sync_period_s
    start = 1000 * index
    return Segment(
        start=start, stop=start + 900, held_from=start, steady_from=start,
        trims=Trims(*trims), amplitude_mA=key.amplitude_mA, position0=0.0,
        microsteps_per_sample=per_sample, periods=int(abs(key.electrical_hz) * 0.9),
        microsteps_per_fullstep=META.microsteps_per_fullstep,
    )


def _observations(seed: int = 1) -> Observations:
    rows = [(c, t) for c in range(len(CONDITIONS)) for t in TRIM_STEPS]
    count = len(rows)
    obs = Observations(
        metadata=META,
        conditions=CONDITIONS,
        condition=np.array([c for c, _ in rows], dtype=np.intp),
        amplitude_A=np.array([CONDITIONS[c].amplitude_mA * 1e-3 for c, _ in rows]),
        omega=np.array([2 * math.pi * CONDITIONS[c].electrical_hz for c, _ in rows]),
        trims=np.array([t for _, t in rows]),
        phasors=np.zeros((count, DIAGNOSIS_ORDERS), dtype=np.complex128),
        sigma=np.full((count, DIAGNOSIS_ORDERS), NOISE_MPS2),
        time_s=np.arange(count, dtype=np.float64),
        segments=tuple(_segment(i, CONDITIONS[c], t) for i, (c, t) in enumerate(rows)),
    )
    spec = ModelSpec(ChainKind.RIGID, frozenset({Effect.DETENT_TORQUE}))
    truth = Model(spec, obs)
    p = truth.layout.start()
    sl = truth.layout.slices
    p[sl["delay_ms"]] = 0.4
    p[sl["load_angle_rad"]] = [0.1 * key.direction for key in CONDITIONS]
    p[sl["amp_offset_mA"]] = (-30.0, 20.0)
    p[sl["amp_gain_error"]] = (0.02, -0.01)
    p[sl["rotor_hz_at_1A"]] = 120.0
    p[sl["rotor_damping_per_s"]] = 60.0
    p[sl["detent"]] = (0.004, 0.002, 0.001, 0.0)
    for _ in range(40):
        motion = Model(spec, obs).predicted(p)
        settled = float(np.abs(motion - obs.phasors).max()) < 1e-9
        obs = replace(obs, phasors=motion)
        if settled:
            break
    assert settled, "the synthetic motion did not settle"
    rng = np.random.default_rng(seed)
    noise = rng.standard_normal((count, DIAGNOSIS_ORDERS, 2)) @ np.array([1.0, 1j])
    return replace(obs, phasors=obs.phasors + noise * NOISE_MPS2 / math.sqrt(2.0))


@pytest.fixture(scope="module")
def diagnosis() -> Diagnosis:
    result = diagnose_observations(_observations())
    assert result.effects, "the synthetic cogging must be named for the page to show an effect"
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
    return re.sub(r"<[^>]+>", " ", re.sub(r"<svg.*?</svg>", " ", page, flags=re.S))


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
    assert "SN1" in text
    assert SOURCE in text
    assert "Mismatch" in text
    assert f"{fit['before']:.3g}" in text
    assert f"{fit['after']:.3g}" in text
    assert f"{fit['after_chi2']:.1f}" in text


def test_report_lists_every_named_effect_with_its_parameters(
    diagnosis: Diagnosis, page: str
) -> None:
    text = _text(page)
    for effect in diagnosis.effects:
        assert effect.effect.value in text
    assert "order_4.peak_percent_of_rated_holding_torque" in text  # flattened, σ beside it
    assert "order_4.sigma_percent" not in text


def test_report_shows_measured_nominal_and_extended_harmonics(page: str) -> None:
    assert page.count("<svg") >= 3
    for legend in ("measured, ±σ", "nominal model", "extended model"):
        assert legend in page
    for order in range(1, DIAGNOSIS_ORDERS + 1):
        assert f"order {order}" in page
    for key in CONDITIONS:
        assert key.label() in page


def test_report_maps_where_the_nominal_model_fails_and_the_trims_drift(page: str) -> None:
    assert "Where the nominal model fails" in page
    assert "χ² per degree of freedom" in page
    assert "optimal offset A (mA)" in page
    assert "optimal gain split (1/10000)" in page


def test_report_tables_located_entries_naming_rounds_and_thresholds(
    diagnosis: Diagnosis, page: str
) -> None:
    text = _text(page)
    harmonic = sum(loc.kind is LocatedKind.HARMONIC for loc in diagnosis.located)
    assert f"{harmonic} harmonic entries located" in text
    assert page.count("<td>harmonic</td>") == min(harmonic, MAX_HARMONIC_ROWS)
    assert f"Round {len(diagnosis.rounds)}:" in text
    for trial in diagnosis.rounds[0].trials:
        assert trial.effect.value in text
    for threshold in ("SIGNIFICANT_CONFIDENCE", "MIN_GAIN_CHI2", "MIN_GAIN_FRACTION",
                      "SEPARABLE_RATIO"):
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
