"""The sensor's self-check at standstill: is it the sensor, mounted as the fixture says?

Before a unit is shaken, the station makes sure the only instrument it trusts
is sound. At rest the sensor must read gravity on the axis the fixture
names and (nearly) nothing on the other two, stream one sample per SYNC, and
be no noisier than the recipe allows. A sensor turned on its mount, a dead
axis, a loose cable or a noisy part each fail one of these, and the run stops
as a station error before any trim is touched.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from station.core import SATURATED_COUNTS, STANDARD_GRAVITY, Axis

MIN_RECEIVED_FRACTION = 0.9
"""Samples that must arrive of those the SYNCs asked for."""
MIN_SAMPLES = 10


@dataclass(frozen=True)
class SelfCheckResult:
    samples_expected: int
    samples_received: int
    mean_mps2: tuple[float, float, float]  # X, Y, Z
    noise_rms_mps2: tuple[float, float, float]
    gravity_axis: Axis
    problems: tuple[str, ...]

    @property
    def ok(self) -> bool:
        return not self.problems

    def as_dict(self) -> dict[str, object]:
        return {
            "samples_expected": self.samples_expected,
            "samples_received": self.samples_received,
            "mean_mps2": list(self.mean_mps2),
            "noise_rms_mps2": list(self.noise_rms_mps2),
            "gravity_axis": self.gravity_axis.value,
            "problems": list(self.problems),
        }


def sensor_self_check(
    counts: NDArray[np.int16],
    lsb_mps2: float,
    *,
    samples_expected: int,
    gravity_axis: Axis,
    gravity_tolerance_mps2: float,
    max_noise_mps2: float,
) -> SelfCheckResult:
    """Judge a standstill capture (raw (n, 3) counts and the sensor's LSB)."""
    problems: list[str] = []
    received = int(counts.shape[0])
    if received < max(MIN_SAMPLES, math.ceil(MIN_RECEIVED_FRACTION * samples_expected)):
        problems.append(
            f"only {received} of {samples_expected} samples arrived at standstill"
        )
    if received == 0:
        zeros = (0.0, 0.0, 0.0)
        return SelfCheckResult(samples_expected, 0, zeros, zeros, gravity_axis, tuple(problems))
    clipped = int(np.count_nonzero(np.abs(counts.astype(np.int32)) >= SATURATED_COUNTS))
    if clipped:
        problems.append(f"{clipped} readings at full scale while standing still")
    acc = counts.astype(np.float64) * lsb_mps2
    mean = acc.mean(axis=0)
    noise = acc.std(axis=0, ddof=1) if received > 1 else np.zeros(3)
    for axis in Axis:
        value = float(mean[axis.column])
        expected = STANDARD_GRAVITY if axis is gravity_axis else 0.0
        if abs(abs(value) - expected) > gravity_tolerance_mps2:
            what = "gravity" if axis is gravity_axis else "no static acceleration"
            problems.append(
                f"axis {axis.value} reads {value:+.2f} m/s² at rest, expected {what} "
                f"({expected:.2f} ± {gravity_tolerance_mps2:g} m/s² in magnitude)"
            )
        # Judged on the raw counts: a float mean leaves a spread of 1e-15 on a stuck axis.
        if received >= MIN_SAMPLES and int(np.ptp(counts[:, axis.column])) == 0:
            problems.append(
                f"axis {axis.value} never changes ({value:+.3f} m/s² in every sample): a live "
                "MEMS axis always shows some noise, so this one is dead or stuck"
            )
        elif float(noise[axis.column]) > max_noise_mps2:
            problems.append(
                f"axis {axis.value} noise {float(noise[axis.column]):.3f} m/s² rms exceeds "
                f"{max_noise_mps2:g} m/s²"
            )
    return SelfCheckResult(
        samples_expected=samples_expected,
        samples_received=received,
        mean_mps2=(float(mean[0]), float(mean[1]), float(mean[2])),
        noise_rms_mps2=(float(noise[0]), float(noise[1]), float(noise[2])),
        gravity_axis=gravity_axis,
        problems=tuple(problems),
    )


MAX_SATURATED_FRACTION = 0.9
"""Readings at full scale a hold may have on any axis. Clipped peaks are dropped by the
analysis, whose fit of the rest stays unbiased (a rough unit before its trims was seen
clipping 43 % of its tangential samples); an axis at full scale nearly all the time
means the element sits at a rail."""


def sensor_in_motion_problems(
    counts: NDArray[np.int16],
    lsb_mps2: float,
    *,
    gravity_axis: Axis,
    gravity_tolerance_mps2: float,
) -> tuple[str, ...]:
    """Why the samples of a hold are not acceleration (empty if they may be).

    The self-check vouches for the sensor before the run; this vouches for it
    during the run, hold by hold, so a sensor that saturates, is unplugged
    (the node then streams zeros) or sticks midway can never yield a ripple
    that passes a limit. Motion does not move the static gravity reading on a
    load turning about a vertical axis, and a live axis is never constant.
    """
    received = int(counts.shape[0])
    if received == 0:
        return ("no sample arrived during the hold",)
    problems: list[str] = []
    clipped = int(np.count_nonzero(np.abs(counts.astype(np.int32)) >= SATURATED_COUNTS,
                                   axis=0).max())
    if clipped > MAX_SATURATED_FRACTION * received:
        problems.append(f"{clipped} of {received} readings at full scale (±{SATURATED_COUNTS}):"
                        " the sensor saturates")
    gravity = float(counts[:, gravity_axis.column].astype(np.float64).mean()) * lsb_mps2
    if abs(abs(gravity) - STANDARD_GRAVITY) > gravity_tolerance_mps2:
        problems.append(f"axis {gravity_axis.value} reads {gravity:+.2f} m/s² on average, not "
                        f"gravity: the MEMS element is unplugged, stuck or no longer mounted")
    if received >= MIN_SAMPLES:
        stuck = [axis.value for axis in Axis if int(np.ptp(counts[:, axis.column])) == 0]
        if stuck:
            problems.append(f"axis {', '.join(stuck)} never changes over {received} samples: "
                            "dead or stuck")
    return tuple(problems)
