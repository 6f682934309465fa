"""What ``station analyze`` prints: plain data, built from an Analysis.

Scripts read the JSON (CLI.md promises ``trims`` and ``segments``); people
read the same numbers as tables. Complex phasors are written as magnitude
and phase (degrees) with their standard uncertainty, which is how a motion
engineer reads a ripple.
"""

from __future__ import annotations

import math
from typing import Any

from station.analysis.estimate import AffineFit, FitQuality, ParabolaFit, TrimEstimate
from station.analysis.pipeline import Analysis, ConditionResult, Measured


def _phasor(h: complex, variance: float) -> dict[str, float]:
    return {
        "magnitude": abs(h),
        "phase_deg": math.degrees(math.atan2(h.imag, h.real)),
        "re": h.real,
        "im": h.imag,
        "sigma": math.sqrt(variance) if math.isfinite(variance) else float("nan"),
    }


def _quality(q: FitQuality) -> dict[str, Any]:
    return {**_figures(q), "residuals": list(q.residuals)}


def _parabola(p: ParabolaFit) -> dict[str, Any]:
    return {
        "axis": p.axis.value,
        "harmonic": p.order,
        "vertex": p.vertex,
        "vertex_sigma": p.vertex_sigma,
        "curvature": p.curvature,
        "floor": p.floor,
        "swept": list(p.swept),
        "points": [
            {"x": x, "power": y, "used": u} for x, y, u in zip(p.x, p.y, p.used, strict=True)
        ],
        "curve": [list(xy) for xy in p.curve()],
        "quality": _quality(p.quality),
    }


def _affine(a: AffineFit) -> dict[str, Any]:
    return {
        "harmonic": a.order,
        "intercept": {"re": a.intercept.real, "im": a.intercept.imag},
        "terms": [
            {"term": t.value, "coefficient": {"re": c.real, "im": c.imag},
             "centre": {"re": m.real, "im": m.imag}}
            for t, c, m in zip(a.terms, a.coefficients, a.centre, strict=True)
        ],
        "quality": _quality(a.quality),
    }


def estimate_dict(e: TrimEstimate) -> dict[str, Any]:
    return {
        "method": e.method.value,
        "trims": e.trims.as_dict(),
        "uncertainty": e.sigma.as_dict(),
        "parabolas": [_parabola(p) for p in e.parabolas],
        "affine": [_affine(a) for a in e.affine],
        "warnings": list(e.warnings),
    }


def fit_summary(e: TrimEstimate) -> dict[str, Any]:
    """The figures of merit of an estimate, small enough to keep with every run.

    The curves and residuals stay in the run's recording, which can be
    analysed again; a results database keeps only what QA filters and plots.
    """
    fits: list[dict[str, Any]] = []
    for p in e.parabolas:
        fits.append({"fit": f"parabola {p.axis.value}", **_figures(p.quality)})
    for a in e.affine:
        fits.append({"fit": f"H{a.order} affine", **_figures(a.quality)})
    return {"method": e.method.value, "fits": fits}


def _figures(q: FitQuality) -> dict[str, Any]:
    return {
        "r_squared": q.r_squared,
        "chi2_reduced": q.chi2_reduced if math.isfinite(q.chi2_reduced) else None,
        "dof": q.dof,
        "points_used": q.points_used,
        "points_available": q.points_available,
    }


def _point(m: Measured, sync_period_s: float) -> dict[str, Any]:
    s, h = m.segment, m.harmonics
    return {
        "trims": s.trims.as_dict(),
        "start_s": s.start * sync_period_s,
        "stop_s": s.stop * sync_period_s,
        "settled_after_s": (s.start - s.steady_from) * sync_period_s,
        "periods": s.periods,
        "samples_used": h.samples_used,
        "samples_missing": h.samples_missing,
        "samples_saturated": m.saturated,
        "h1": _phasor(h.h(1), h.var(1)),
        "h2": _phasor(h.h(2), h.var(2)),
        "harmonics": [
            _phasor(complex(p), float(v)) for p, v in zip(h.phasors, h.variance, strict=True)
        ],
        "residual_rms": h.residual_rms,
    }


def _condition(r: ConditionResult, sync_period_s: float) -> dict[str, Any]:
    c = r.condition
    return {
        "amplitude_mA": c.amplitude_mA,
        "electrical_hz": c.electrical_hz,
        "segments": len(c.measured),
        "method": r.estimate.method.value if r.estimate else None,
        "trims": r.estimate.trims.as_dict() if r.estimate else None,
        "estimates": {m.value: estimate_dict(e) for m, e in r.estimates.items()},
        "unsupported": {m.value: reason for m, reason in r.unsupported.items()},
        "points": [_point(m, sync_period_s) for m in c.measured],
    }


def analysis_dict(a: Analysis, recording: str) -> dict[str, Any]:
    """The JSON document of ``station analyze``."""
    tl = a.timeline
    period = tl.sync_period_s
    e = a.estimate
    losses = tl.losses
    return {
        "recording": recording,
        "serial": tl.metadata.serial,
        "method": e.method.value,
        "trims": e.trims.as_dict(),
        "uncertainty": e.sigma.as_dict(),
        "segments": a.segments_used,
        "condition": {
            "amplitude_mA": a.primary.condition.amplitude_mA,
            "electrical_hz": a.primary.condition.electrical_hz,
        },
        "fit": estimate_dict(e),
        "warnings": [*a.warnings, *e.warnings],
        "samples": tl.samples,
        "duration_s": tl.samples * period,
        "losses": {
            "syncs_seen": losses.syncs_seen,
            "syncs_missing": losses.syncs_missing,
            "sensor_samples_lost": losses.sensor_samples_lost,
            "drive_status_lost": losses.drive_status_lost,
            "drive_trims_lost": losses.drive_trims_lost,
            "saturated_samples": losses.saturated_samples,
            "frames_ignored": losses.frames_ignored,
            "frames_malformed": losses.frames_malformed,
        },
        "rejected": [
            {"start_s": r.start * period, "stop_s": r.stop * period, "reason": r.reason}
            for r in a.rejected
        ],
        "conditions": [_condition(r, period) for r in a.conditions],
    }
