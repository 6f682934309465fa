"""Current distortion: each phase current off its sine, in either of the two forms drives
make it: a waveform with harmonics 2 to 5 of the commutation angle (a table or a loop that
distorts in proportion to the current), or the bridge's dead time, a current error of fixed
size against the current's sign. The torque carries both as ripple; the dead time's, of
fixed size and four times an electrical period, looks like cogging, except that it follows
the currents' angle where cogging follows the rotor's, and it grows with the holding
current only through the magnet's torque weights (an independent simulator's dead-time
recording was named ``detent_torque`` while the model had only the waveform)."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import harmonic_pairs, sigmas
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.observations import Observations

DISTORTION_ORDERS = (2, 3, 4, 5)
"""Harmonics h of each phase current's waveform."""

DEAD_TIME_KNEE = 0.025
"""Where the dead time's error turns from one sign to the other, as a share of the rated
current (the PWM ripple's half-width, 1-4 % on real drives): held fixed, since at the
characterization's currents the turn spans a few hundredths of a radian of the
commutation angle, far below what the recorded orders resolve."""
DEAD_TIME_MAX = 0.15
"""The largest dead-time error per phase, as a share of the rated current: a drive that
loses more than that at every zero crossing is broken, not distorting."""


def dead_time_knee_A(obs: Observations) -> float:
    return DEAD_TIME_KNEE * obs.metadata.rated_current_mA * 1e-3


def blocks(spec: ModelSpec, obs: Observations) -> list[Block]:
    rated_A = obs.metadata.rated_current_mA * 1e-3
    return [Block("distortion", 4 * len(DISTORTION_ORDERS), 0.0, -0.25, 0.25,
                  BlockKind.LINEAR),
            # Each phase's dead-time error (A), never negative: it is against the current.
            Block("dead_time", 2, 0.0, 0.0, DEAD_TIME_MAX * rated_A, BlockKind.LINEAR)]


def readout(fit: Fit, cov: NDArray[np.float64]) -> dict[str, Any]:
    sig = sigmas(cov)
    # The block counts each pair's second coefficient the other way round.
    out: dict[str, Any] = harmonic_pairs(fit, sig, "distortion", DISTORTION_ORDERS,
                                         scale=100.0, key="relative_to_fundamental_percent",
                                         conjugate=True)
    sl = fit.model.layout.slices["dead_time"]
    dead, err = fit.params[sl], sig[sl]
    rated_mA = fit.model.rated_A * 1e3
    out["dead_time"] = {
        "error_a_mA": 1e3 * float(dead[0]), "error_a_sigma_mA": 1e3 * float(err[0]),
        "error_b_mA": 1e3 * float(dead[1]), "error_b_sigma_mA": 1e3 * float(err[1]),
        "knee_mA": DEAD_TIME_KNEE * rated_mA,
        "law": "i − error·tanh(i/knee) on each phase, after the waveform",
    }
    return out


TERMS = EffectTerms(
    effect=Effect.CURRENT_DISTORTION,
    blocks=blocks,
    readout=readout,
    healthy_part=(
        "Nothing kept: every drive's waveform is a little off, but what the recording "
        "resolves moves the optimal trims and the ripple, so it is named."),
    rivals={
        Effect.DETENT_TORQUE: (
            "record the drive's phase currents, or run at more currents: cogging does not "
            "change with current, distortion torque grows with it"),
    },
    grid_shared=True,
)
