"""The paper's method: three sweeps, closed loop. Offset A over [min, max] with B at 0,
then B with A at its vertex, then the gain split with both offsets at theirs; each
parabola of |H1|² (or |H2|²) against its trim has its vertex at the trim that nulls it.
Magnitudes only, so it needs nothing of the drive but its trims."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING, Any, Final

from station.core import GAIN_LIMITS, GAIN_UNITY, Method, Trims, offset_limit_mA
from station.methods import Batch, Plan, SweepContext, settings_of
from station.methods.tables import negated, span
from station.schedules import Phase
from station.tomltable import TomlTable

if TYPE_CHECKING:
    from station.analysis.estimate import ParabolaFit, TrimAxis, TrimEstimate

GAIN_SUM: Final = 2 * GAIN_UNITY


@dataclass(frozen=True)
class PaperSweep:
    """The paper's three sweeps, closed loop: offset A over [min, max] with B at
    0, then B with A at its estimate, then gain A over [gain_min, gain_max] with
    gain B = 20000 - gain A and the offsets at their estimates."""

    offset_min_mA: int
    offset_max_mA: int
    offset_points: int
    gain_min: int
    gain_max: int
    gain_points: int


def paper_order() -> tuple[tuple[Phase, TrimAxis], ...]:
    """The paper's order: each sweep with the trims swept before it at their vertices."""
    from station.analysis.estimate import TrimAxis  # noqa: PLC0415 - the estimators

    return ((Phase.SWEEP_OFFSET_A, TrimAxis.OFFSET_A), (Phase.SWEEP_OFFSET_B, TrimAxis.OFFSET_B),
            (Phase.SWEEP_GAIN, TrimAxis.GAIN_SPLIT))


def from_vertices(fits: Sequence[ParabolaFit]) -> TrimEstimate:
    """The paper's estimate from its three parabolas, in ``paper_order``."""
    from station.analysis.estimate import TrimEstimate, TrimSigma  # noqa: PLC0415
    from station.designs import with_split  # noqa: PLC0415

    a, b, g = fits
    trims = with_split(Trims(a.vertex, b.vertex, GAIN_UNITY, GAIN_UNITY), g.vertex)
    return TrimEstimate(
        method=Method.PAPER,
        trims=trims,
        sigma=TrimSigma(a.vertex_sigma, b.vertex_sigma, g.vertex_sigma, g.vertex_sigma),
        parabolas=(a, b, g),
    )


def at_vertex(centre: Trims, fit: ParabolaFit) -> Trims:
    """``centre`` moved to a parabola's vertex along its axis."""
    from station.analysis.estimate import TrimAxis  # noqa: PLC0415
    from station.designs import with_split  # noqa: PLC0415

    if fit.axis is TrimAxis.OFFSET_A:
        return replace(centre, offset_a_mA=fit.vertex)
    if fit.axis is TrimAxis.OFFSET_B:
        return replace(centre, offset_b_mA=fit.vertex)
    return with_split(centre, fit.vertex)


def middle(points: Sequence[Trims]) -> Trims:
    """The middle of an axis sweep: where its clipped ends move towards."""
    n = len(points)
    return Trims(sum(p.offset_a_mA for p in points) / n, sum(p.offset_b_mA for p in points) / n,
                 sum(p.gain_a for p in points) / n, sum(p.gain_b for p in points) / n)


class PaperMethod:
    name = "paper"
    settings_type = PaperSweep
    table = "sweep"
    needs_angle = False
    estimates = Method.PAPER

    def read(self, t: TomlTable, rated_mA: int | None) -> PaperSweep:
        half = offset_limit_mA(rated_mA) if rated_mA is not None else None
        offset_note = "the drive's offset range: half of product.rated_current_mA"
        offset_note = offset_note if half is not None else ""
        # 20000 - g lies in 5000..15000 exactly when g does, so one range check covers
        # both phases' gains.
        gain_note = f"and gain B = {GAIN_SUM} - gain A must be too"
        sweep = PaperSweep(
            offset_min_mA=t.integer("offset_min_mA", negated(half), half, note=offset_note),
            offset_max_mA=t.integer("offset_max_mA", negated(half), half, note=offset_note),
            offset_points=t.integer("offset_points", 3, 101),
            gain_min=t.integer("gain_min", *GAIN_LIMITS, note=gain_note),
            gain_max=t.integer("gain_max", *GAIN_LIMITS, note=gain_note),
            gain_points=t.integer("gain_points", 3, 101),
        )
        offsets = (sweep.offset_min_mA, sweep.offset_max_mA)
        span(t, ("offset_min_mA", "offset_max_mA"), offsets, 0)
        span(t, ("gain_min", "gain_max"), (sweep.gain_min, sweep.gain_max), GAIN_UNITY)
        return sweep

    def plan(self, settings: Any, ctx: SweepContext) -> Plan:
        """The three sweeps in order, each centred on the previous vertices."""
        from station.analysis.estimate import TrimAxis, fit_parabola  # noqa: PLC0415
        from station.designs import gain_sweep, offset_a_sweep, offset_b_sweep  # noqa: PLC0415

        sweep = settings_of(settings, PaperSweep)
        fits: list[ParabolaFit] = []
        for phase, axis in paper_order():
            if axis is TrimAxis.OFFSET_A:
                points = offset_a_sweep(sweep.offset_min_mA, sweep.offset_max_mA,
                                        sweep.offset_points)
            elif axis is TrimAxis.OFFSET_B:
                points = offset_b_sweep(fits[0].vertex, sweep.offset_min_mA,
                                        sweep.offset_max_mA, sweep.offset_points)
            else:
                points = gain_sweep(fits[0].vertex, fits[1].vertex, sweep.gain_min,
                                    sweep.gain_max, sweep.gain_points)
            measured = yield Batch(tuple(points), phase, f"{phase.value}: {len(points)} points",
                                   centre=middle(points))
            ctx.estimating(axis.value)
            fit, warnings = fit_parabola([m.point() for m in measured], axis)
            for warning in warnings:
                ctx.warn(warning)
            fits.append(fit)
        return from_vertices(fits)


METHOD: Final = PaperMethod()
