"""The paper's parabolas in rounds, for drives whose electrical angle is unknown (a
Modbus drive reports no SYNC-locked position, ICD.md §4): per round, offset A, then
offset B, then the gain split, each swept over ±span around the latest estimate, so the
last round's parabolas sit close to the null where they are nearly exact."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, Final

from station.core import Method, offset_limit_mA
from station.methods import Batch, Plan, SweepContext, settings_of, trims_text
from station.methods.paper import at_vertex, from_vertices, paper_order
from station.methods.tables import HALF_RATED_NOTE, MAX_GAIN_STEP, rounds, same_rounds
from station.tomltable import TomlTable

if TYPE_CHECKING:
    from station.analysis.estimate import ParabolaFit


@dataclass(frozen=True)
class MagnitudeSweep:
    """Rounds of the paper's parabolas around the latest estimate."""

    offset_spans_mA: tuple[int, ...]
    gain_spans: tuple[int, ...]
    points: int
    # Holds of its own (None: the motion table's). A trim written over Modbus takes
    # effect somewhere between its sending and its acknowledgement, and those samples
    # are not used, so these holds cannot be as short as a CANopen star's.
    settle_periods: int | None = None
    dwell_periods: int | None = None


class MagnitudeMethod:
    name = "magnitude"
    settings_type = MagnitudeSweep
    table = "magnitude_sweep"
    needs_angle = False
    estimates = Method.PAPER

    def read(self, t: TomlTable, rated_mA: int | None) -> MagnitudeSweep:
        half = offset_limit_mA(rated_mA) if rated_mA is not None else None
        sweep = MagnitudeSweep(
            offset_spans_mA=rounds(t, "offset_spans_mA", half, HALF_RATED_NOTE),
            gain_spans=rounds(t, "gain_spans", MAX_GAIN_STEP, ""),
            points=t.integer("points", 3, 21),
            settle_periods=(t.integer("settle_periods", 0, 1000) if t.has("settle_periods")
                            else None),
            dwell_periods=(t.integer("dwell_periods", 3, 10000) if t.has("dwell_periods")
                           else None),
        )
        same_rounds(t, "offset_spans_mA", "gain_spans",
                    (len(sweep.offset_spans_mA), len(sweep.gain_spans)))
        t.finish()
        return sweep

    def plan(self, settings: Any, ctx: SweepContext) -> Plan:
        """Within a round each axis is swept with the previous axes already at their
        new vertices, as the paper does; the last round gives the estimate."""
        from station.analysis.estimate import TrimAxis, fit_parabola  # noqa: PLC0415
        from station.designs import axis_sweep, within_drive_range  # noqa: PLC0415

        sweep = settings_of(settings, MagnitudeSweep)
        rated = ctx.recipe.product.rated_current_mA
        centre = ctx.centre
        spans = list(zip(sweep.offset_spans_mA, sweep.gain_spans, strict=True))
        fits: list[ParabolaFit] = []
        for number, (offset_span, gain_span) in enumerate(spans, start=1):
            fits = []
            for phase, axis in paper_order():
                span = gain_span if axis is TrimAxis.GAIN_SPLIT else offset_span
                points = axis_sweep(centre, axis, span, sweep.points, rated)
                measured = yield Batch(
                    tuple(points), phase,
                    f"round {number}/{len(spans)}: {axis.value} ±{span} around "
                    f"{trims_text(centre)}",
                    centre=centre, settle_periods=sweep.settle_periods,
                    dwell_periods=sweep.dwell_periods)
                fit, warnings = fit_parabola([m.point() for m in measured], axis)
                if number == len(spans):
                    for warning in warnings:
                        ctx.warn(warning)
                fits.append(fit)
                centre = within_drive_range(at_vertex(centre, fit), rated)
        return from_vertices(fits)


METHOD: Final = MagnitudeMethod()
