"""Where the recording and the nominal model disagree: per order and condition, in the
trims' "constants" drifting from one condition to another, on another sensor axis, and in
parameters the data pull past a limit (``diagnose`` step 3)."""

from __future__ import annotations

import math
from collections.abc import Iterable

import numpy as np
from numpy.typing import NDArray
from scipy import stats

from station.core import GAIN_UNITY
from station.diagnosis.axes import AxisCoupling
from station.diagnosis.fit import Fit, ParameterJudgement, ParameterState, sigmas, solve_linear
from station.diagnosis.model import Model
from station.diagnosis.observations import ConditionKey
from station.diagnosis.results import Candidate, Finding, Located, LocatedKind

SIGNIFICANT_CONFIDENCE = 0.999
"""A residual, a drift or a term group counts when noise alone would produce it less than
once in a thousand."""


def chi2_confidence(chi2: float, dof: int) -> float:
    return float(stats.chi2.cdf(chi2, dof)) if dof > 0 else 0.0


def chi2_map(result: Fit, residuals: NDArray[np.float64] | None = None
             ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """χ² per condition and order, (C, K), and the degrees of freedom per condition, (C,):
    both parts of every segment's phasor (a fit's own residuals unless given)."""
    obs = result.model.obs
    r = result.residuals if residuals is None else residuals
    res = r[:result.model.harmonic_values].reshape(2, obs.count, obs.orders)
    per_segment = (res**2).sum(axis=0)  # (S, K)
    conditions = len(obs.conditions)
    chi2 = np.zeros((conditions, obs.orders))
    np.add.at(chi2, obs.condition, per_segment)
    dof = 2 * np.bincount(obs.condition, minlength=conditions)
    return chi2, dof


def locate_harmonics(result: Fit, residuals: NDArray[np.float64] | None = None,
                     kind: LocatedKind = LocatedKind.HARMONIC) -> list[Located]:
    """Per condition and order: χ² of a residual against the noise."""
    obs = result.model.obs
    r = result.residuals if residuals is None else residuals
    chi2, dofs = chi2_map(result, r)
    in_mps2 = result.model.in_mps2(r)
    out: list[Located] = []
    for c, key in enumerate(obs.conditions):
        rows = obs.condition == c
        dof = int(dofs[c])
        for k in range(obs.orders):
            value = float(chi2[c, k])
            conf = chi2_confidence(value, dof)
            if conf < SIGNIFICANT_CONFIDENCE:
                continue
            physical = in_mps2[:, rows, k]
            out.append(
                Located(
                    kind=kind,
                    chi2=value,
                    dof=dof,
                    confidence=conf,
                    condition=key,
                    order=k + 1,
                    residual_rms_mps2=float(np.sqrt(np.mean((physical**2).sum(axis=0)))),
                    measured_rms_mps2=float(np.sqrt(np.mean(np.abs(obs.phasors[rows, k]) ** 2))),
                )
            )
    out.sort(key=lambda loc: loc.chi2, reverse=True)
    return out


def bend_finding(bent: Candidate, unbent: Candidate) -> Finding:
    """The sensor's bent transfer in words: physics the station models but has no id for."""
    where = bent.fit.model.layout.slices["sensor_bend"]
    c2, c3 = bent.fit.params[where]
    s2, s3 = sigmas(bent.fit)[where]
    gain = unbent.held.total - bent.held.total
    return Finding(
        f"the sensor's transfer bends: its tangential axis reads a + c2·a²/FS + c3·a³/FS² "
        f"with c2 = {c2:+.4f} ± {s2:.4f} and c3 = {c3:+.4f} ± {s3:.4f} (FS its full scale; "
        f"worst deviation {100 * (abs(c2) + abs(c3)):.1f} % of FS), so products of the "
        "strongest orders appear at their sums and differences whatever the current or "
        "speed. No id of the vocabulary describes this; modelled, the held-out χ² falls "
        f"from {unbent.held.total:.0f} to {bent.held.total:.0f}. Recording with a range "
        "where the ripple uses less of the full scale shrinks it",
        "sensor_bend", gain,
        {"c2": float(c2), "c2_sigma": float(s2), "c3": float(c3), "c3_sigma": float(s3)})


def locate_axis(coupled: AxisCoupling, conditions: tuple[ConditionKey, ...]) -> list[Located]:
    """The cells where another sensor axis carries the tangential ripple, strongest first."""
    out = []
    for cell in coupled.cells:
        conf = chi2_confidence(cell.chi2, cell.dof)
        if conf >= SIGNIFICANT_CONFIDENCE:
            out.append(Located(LocatedKind.SENSOR_AXIS, cell.chi2, cell.dof, conf,
                               conditions[cell.condition], cell.order, cell.axis_rms_mps2,
                               cell.tangential_rms_mps2, parameter=coupled.axis.value))
    out.sort(key=lambda loc: loc.chi2, reverse=True)
    return out


def trim_constants(offsets_mA: NDArray[np.float64], gain_errors: NDArray[np.float64]
                   ) -> tuple[float, float, float]:
    """The amplifier's constants as the trims that null them: offsets A and B (mA)
    and the gain split (1/10000, half the A−B gain difference)."""
    return (-float(offsets_mA[0]), -float(offsets_mA[1]),
            -float(gain_errors[0] - gain_errors[1]) / 2.0 * GAIN_UNITY)


def per_condition_constants(nominal: Fit) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The optimal trims re-estimated at each condition alone, and their σ, (C, 3).

    Columns: offset A, offset B (mA, the negated amplifier offsets) and the gain
    split (1/10000, half the A−B gain difference that nulls the imbalance). The
    chain, timing and load angles stay at the nominal fit; only the amplifier's
    constants are solved again on each condition's segments.
    """
    obs = nominal.model.obs
    conditions = len(obs.conditions)
    values = np.full((conditions, 3), np.nan)
    errors = np.full((conditions, 3), np.nan)
    for c in range(conditions):
        sub = obs.subset(obs.condition == c)
        model = Model(nominal.model.spec, sub)
        p = model.layout.start()
        for block in nominal.model.layout.blocks:
            if block.name == "load_angle_rad":
                p[model.layout.slices[block.name]] = nominal.value(block.name)[c]
            else:
                p[model.layout.slices[block.name]] = nominal.value(block.name)
        p = solve_linear(model, p, passes=3)
        _, design = model.linear_design(p)
        jac = design.T
        try:
            cov = np.linalg.inv(jac.T @ jac)
        except np.linalg.LinAlgError:
            continue
        sl = model.layout.slices
        idx = model.linear_index().tolist()
        ia = idx.index(sl["amp_offset_mA"].start)
        ib = ia + 1
        ga = idx.index(sl["amp_gain_error"].start)
        gb = ga + 1
        values[c] = trim_constants(p[sl["amp_offset_mA"]], p[sl["amp_gain_error"]])
        split_var = (cov[ga, ga] + cov[gb, gb] - 2 * cov[ga, gb]) / 4.0 * GAIN_UNITY**2
        errors[c] = np.sqrt(np.maximum([cov[ia, ia], cov[ib, ib], split_var], 0.0))
    return values, errors


def locate_drift(values: NDArray[np.float64], errors: NDArray[np.float64],
                 conditions: tuple[ConditionKey, ...]) -> list[Located]:
    """Constants of the nominal model that differ between conditions beyond their σ
    (``values``/``errors`` from ``per_condition_constants``)."""
    amps = np.array([c.amplitude_mA for c in conditions], dtype=float)
    out: list[Located] = []
    for column, name in enumerate(("optimal_offset_a_mA", "optimal_offset_b_mA",
                                   "optimal_gain_split")):
        v, s = values[:, column], errors[:, column]
        ok = np.isfinite(v) & np.isfinite(s) & (s > 0)
        if ok.sum() < 2:
            continue
        w = 1.0 / s[ok] ** 2
        mean = float(np.sum(w * v[ok]) / np.sum(w))
        chi2 = float(np.sum(w * (v[ok] - mean) ** 2))
        dof = int(ok.sum()) - 1
        conf = chi2_confidence(chi2, dof)
        if conf < SIGNIFICANT_CONFIDENCE:
            continue
        slope = np.polyfit(amps[ok], v[ok], 1, w=np.sqrt(w))[0] if len(set(amps[ok])) > 1 else 0
        out.append(
            Located(
                kind=LocatedKind.PARAMETER_DRIFT,
                chi2=chi2,
                dof=dof,
                confidence=conf,
                parameter=name,
                values=tuple(float(x) for x in v),
                sigmas=tuple(float(x) for x in s),
                trend=f"{slope * 1000:+.2f} per A of current amplitude",
            )
        )
    return out


def bound_findings(judgements: Iterable[ParameterJudgement]) -> list[Finding]:
    """The nominal parameters the data pull past a physical limit, in words."""
    out = []
    for j in judgements:
        if j.state is not ParameterState.PUSHED:
            continue
        shown = _readable(j.name, j.bound if j.bound is not None else j.value)
        out.append(Finding(
            f"the nominal model cannot describe this recording: {shown[0]} sits at its "
            f"physical limit {shown[1]} and the data pull it further (χ² would fall by "
            f"{j.chi2_gain:.0f})", j.name, j.chi2_gain))
    return out


def _readable(name: str, value: float) -> tuple[str, str]:
    if name.startswith("log_"):
        return name[4:], f"{math.exp(value):.4g}"
    return name, f"{value:.4g}"
