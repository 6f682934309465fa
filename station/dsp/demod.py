"""Synchronous demodulation: harmonics of a signal referenced to an angle.

The calibration looks for ripple at known multiples of the electrical angle
the drive itself commands; correlating with exp(−j·k·angle) isolates exactly
those orders and rejects noise and every other order, provided the samples
span whole electrical periods (then the other orders are orthogonal).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray


def harmonic_phasors(
    signal: ArrayLike, angle: ArrayLike, orders: Sequence[int]
) -> NDArray[np.complex128]:
    """H_k = (2/N)·Σ s·exp(−j·k·angle) for each order k.

    A component A·cos(k·angle + φ) yields H_k = A·e^(jφ): the magnitude is the
    amplitude and the argument the phase relative to the reference angle.
    The caller passes samples spanning whole periods of the angle.
    """
    s = np.asarray(signal, dtype=np.float64)
    a = np.asarray(angle, dtype=np.float64)
    if s.ndim != 1 or s.shape != a.shape:
        raise ValueError(f"signal and angle must be 1-D and equally long, got {s.shape}, {a.shape}")
    if s.size == 0:
        raise ValueError("no samples to demodulate")
    scale = 2.0 / s.size
    out = np.empty(len(orders), dtype=np.complex128)
    for n, k in enumerate(orders):
        out[n] = scale * np.dot(s, np.exp(-1j * k * a))
    return out
