"""How much a hold's clipped samples could move its phasors.

The harmonic fit leaves a clipped sample out, and in effect puts in its place what
the fitted orders predict there. Where the waveform's peak is over the sensor's
rail at the same electrical phase in every period, that prediction is all the fit
ever has of those phases, and an error δ in one sample of n moves every order's
phasor by up to 2δ/n. A development disk whose flux harmonics peaked 10 m/s² over
±16 g in one sample of 50 read H1 0.014 m/s² where the plant has 0.42 (seed
1742693704): the samples that were not there decided the harmonic.

What is over the rail cannot be measured, but a smooth peak that crosses the rail
with slope s and stays over it for w samples rises about s·w/4 above it (a
parabola's cap). The slope is what the samples beside the run show. So each clipped
sample lay somewhere between the rail and that cap, and may differ from what the fit
put there by as much as the farther of the two: on a synthetic hold with content
beyond the fitted orders, 4 % clipped, H1 moved by 14.4 m/s², and the bound is 23.2
(9.0 without the fit's own stand-in, too little). The phasors carry the sum as an
uncertainty of their own: the estimate weighs a hold by it and, as one bias every
clipped hold shares, carries it in its σ; the verification judges the ripple with it.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray


def clipped_runs(at_rail: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """[start, stop) of each run of consecutive samples at the rail."""
    flags = np.concatenate([[False], at_rail.astype(np.bool_), [False]])
    edges = np.flatnonzero(flags[1:] != flags[:-1])
    return [(int(a), int(b)) for a, b in zip(edges[::2], edges[1::2], strict=True)]


def _slope_into(signal: NDArray[np.float64], run: tuple[int, int], sign: float, rail: float
                ) -> float | None:
    """The steepest the waveform could have been where it crossed into ``run``: the step
    from each unclipped neighbour to the rail, and each neighbour's own step beside it.
    None where no neighbour was measured."""
    a, b = run
    n = signal.size
    slopes = []
    for edge, beyond in ((a - 1, a - 2), (b, b + 1)):
        if not 0 <= edge < n or not math.isfinite(signal[edge]):
            continue
        slopes.append(rail - sign * float(signal[edge]))
        if 0 <= beyond < n and math.isfinite(signal[beyond]):
            slopes.append(abs(float(signal[edge] - signal[beyond])))
    return max(slopes) if slopes else None


def hidden_by_clipping(signal: NDArray[np.float64], counts: NDArray[np.int64],
                       at_rail: NDArray[np.bool_], rail_mps2: float, *,
                       imputed: NDArray[np.float64],
                       weights: NDArray[np.float64] | None = None) -> float:
    """The most a hold's samples over the rail could move any order's phasor (m/s²).

    ``signal`` is the hold's acceleration in m/s² (NaN where lost or clipped),
    ``counts`` the same axis's raw counts (the sign of each clip), ``at_rail`` where
    that axis read full scale and ``imputed`` what the harmonic fit put in each
    sample's place (``Harmonics.imputed``, spread over the hold; read only at the
    rail). A sample of a run of w clipped samples lay between the rail and
    s·(w + 1)/4 beyond it (``_slope_into``; w + 1 because the waveform may have crossed
    the rail just after the last sample below it), and each phasor moves by 2/n of how
    far that is from what the fit put there, at most; with ``weights`` (a taper), by
    2·wⱼ/Σw. A run whose neighbours were both lost takes the steepest step the hold
    shows anywhere, into any run or between any two samples.
    """
    n = signal.size
    runs = clipped_runs(at_rail)
    if not runs or n == 0:
        return 0.0
    signs = [1.0 if counts[run[0]] > 0 else -1.0 for run in runs]
    slopes = [_slope_into(signal, run, sign, rail_mps2)
              for run, sign in zip(runs, signs, strict=True)]
    steps = np.abs(np.diff(signal))
    finite = steps[np.isfinite(steps)]
    steepest = max([float(finite.max()) if finite.size else 2.0 * rail_mps2,
                    *(s for s in slopes if s is not None)])
    weight = np.ones(n) if weights is None else weights
    hidden = 0.0
    for (start, stop), sign, slope in zip(runs, signs, slopes, strict=True):
        width = stop - start
        beyond = (steepest if slope is None else slope) * (width + 1) / 4.0
        put = sign * imputed[start:stop]  # towards the rail: positive
        far = np.maximum(np.abs(rail_mps2 - put), np.abs(rail_mps2 + beyond - put))
        hidden += float(np.sum(weight[start:stop] * far))
    return 2.0 * hidden / float(np.sum(weight))
