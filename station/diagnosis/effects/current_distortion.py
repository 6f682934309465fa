"""Current distortion: each phase current off its sine, in either of the two forms drives
make it: a waveform with harmonics 2 to 5 of the commutation angle (a table or a loop that
distorts in proportion to the current), or the bridge's dead time, a current error of fixed
size against the current's sign. The torque carries both as ripple; the dead time's, of
fixed size and four times an electrical period, looks like cogging, except that it follows
the currents' angle where cogging follows the rotor's, and it grows with the holding
current only through the magnet's torque weights (an independent simulator's dead-time
recording was named ``detent_torque`` while the model had only the waveform)."""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from station.core import Effect
from station.diagnosis.effects import EffectTerms
from station.diagnosis.effects.readings import harmonic_pairs, sigmas
from station.diagnosis.hooks import Grid, Hooks, Kept, Params, Phasors, Role, TorqueParts
from station.diagnosis.layout import Block, BlockKind

if TYPE_CHECKING:
    from station.diagnosis.fit import Fit
    from station.diagnosis.layout import ModelSpec
    from station.diagnosis.model import Model
    from station.diagnosis.motion import Motion
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


QUARTER = math.pi / 2.0


def current_wave(model: Model, p: Params) -> tuple[Phasors, Phasors]:
    # Phase B's harmonic h is turned by h quarter periods: its waveform is phase A's, a
    # quarter of the commutation angle later.
    c = model.block(p, "distortion")
    wave_a = [c[4 * i] - 1j * c[4 * i + 1] for i in range(len(DISTORTION_ORDERS))]
    wave_b = [(c[4 * i + 2] - 1j * c[4 * i + 3]) * np.exp(-1j * h * QUARTER)
              for i, h in enumerate(DISTORTION_ORDERS)]
    return np.asarray(wave_a, dtype=np.complex128), np.asarray(wave_b, dtype=np.complex128)


def _before(model: Model, p: Params) -> tuple[Grid, Grid]:
    """Each phase's current before its dead time, on the current role's finer grid (kept:
    the currents, their dead time's turns and its share of the bases all start from it)."""
    def made() -> tuple[Grid, Grid]:
        dc_a, ac_a, dc_b, ac_b = model.current_coefficients(p)
        fine = model.fine_synth
        return dc_a + (ac_a @ fine).real, dc_b + (ac_b @ fine).real
    out: tuple[Grid, Grid] = model.kept("dead_time_before", Role.CURRENTS).get(p, made)
    return out


def dead_time_taken(model: Model, p: Params) -> tuple[Grid, Grid]:
    """How much of a change in each phase's current before its dead time the dead time
    takes back, on the finer grid: (D/knee)·sech²(i/knee), large only where it turns."""
    dead = model.block(p, "dead_time")
    knee = dead_time_knee_A(model.obs)
    out = tuple(d / knee / np.cosh(i / knee) ** 2
                for d, i in zip(dead, _before(model, p), strict=True))
    return out[0], out[1]


def dead_time_turns(model: Model, p: Params) -> tuple[Grid, Grid]:
    """tanh(i/knee) of each phase's current before its dead time, on the grid: the shape a
    dead-time error of one ampere takes, band-limited (``Model.band_limited``)."""
    def made() -> tuple[Grid, Grid]:
        before_a, before_b = _before(model, p)
        knee = dead_time_knee_A(model.obs)
        return (model.band_limited(np.tanh(before_a / knee)),
                model.band_limited(np.tanh(before_b / knee)))
    out: tuple[Grid, Grid] = model.kept("dead_time_turns", Role.CURRENTS).get(p, made)
    return out


def current_made(model: Model, p: Params, i_a: Grid, i_b: Grid) -> tuple[Grid, Grid]:
    dead = model.block(p, "dead_time")
    turn_a, turn_b = dead_time_turns(model, p)
    return i_a - dead[0] * turn_a, i_b - dead[1] * turn_b


def current_kept(model: Model, p: Params, before: Kept) -> Kept:
    taken = dead_time_taken(model, p)

    def kept(phase: int, base: Grid, d_i: Grid, fine: Grid | float) -> Grid:
        # As the phase carries it: less what the dead time takes back where the current
        # turns (``fine``: the change on the finer grid).
        out: Grid = before(phase, base, d_i, fine) - d_i * model.band_limited(
            taken[phase] * fine)
        return out
    return kept


def bases(model: Model, p: Params, m: Motion, parts: TorqueParts) -> list[Grid]:
    lag_a, lag_b = model.current_response(p)
    gain = 1.0 + model.block(p, "amp_gain_error")
    ga = gain[0] * model.trim_gain[:, :1] * model.amp
    gb = gain[1] * model.trim_gain[:, 1:] * model.amp
    out: list[Grid] = []
    for h in DISTORTION_ORDERS:
        col = model.current_column(h)
        za = ga[:, 0] * lag_a[:, col]
        zb = gb[:, 0] * lag_b[:, col] * np.exp(-1j * h * QUARTER)
        wave = model.current_synth[col][None, :]
        fine = model.fine_synth[col][None, :]
        for phase, z, d_i in ((0, za, parts.d_ia), (1, zb, parts.d_ib)):
            for turn in (1.0, -1j):
                out.append(parts.kept(phase, d_i * (turn * z[:, None] * wave).real, d_i,
                                      (turn * z[:, None] * fine).real))
    turn_a, turn_b = dead_time_turns(model, p)
    return [*out, -parts.d_ia * turn_a, -parts.d_ib * turn_b]


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
    hooks=Hooks(reads={Role.CURRENTS: ("distortion", "dead_time")},
                current_orders=DISTORTION_ORDERS, current_wave=current_wave,
                current_made=current_made, current_kept=current_kept, bases=bases),
)
