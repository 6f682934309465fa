"""Vocabulary shared by the physics, the devices, the drivers and the CLI."""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from enum import StrEnum
from typing import Any

Mapper = Callable[..., Iterable[Any]]
"""``map``, or an executor's: how independent pieces of work are run (side by side in
worker processes, or one by one), in order either way, so the answer is the same."""

GAIN_UNITY = 10000
"""Gains are in 1/10000 (ICD.md): 10000 means 1.0."""

STANDARD_GRAVITY = 9.80665
"""m/s² per g: the sensor's sensitivity is range·g/32768 (ICD.md §3, 0x2001)."""
SENSOR_RANGES_G = (2, 4, 8, 16)
"""Full-scale ranges of the acceleration sensor (ICD.md §3, object 0x2000)."""
SATURATED_COUNTS = 32767
"""A saturated sample reads ±32767 (ICD.md §3), never -32768."""
SENSOR_COUNTER_MODULUS = 1 << 16
"""The sensor's sample counter (ICD.md §3, object 0x2010) is a U16 that wraps."""
GAIN_LIMITS = (5000, 15000)
"""The drive accepts phase gains in 5000..15000 (ICD.md §2, 0x2100:03/04)."""


class Method(StrEnum):
    """How trims are estimated, in one word for the recipe that asks, the result that
    reports it and the analysis that redoes it: the paper's parabolas of |H1|² and |H2|²
    against each trim (also what a drive without its angle allows), or the phase-coherent
    affine maps of both harmonics around the latest estimate."""

    PAPER = "paper"
    COHERENT = "coherent"

    @property
    def needs_angle(self) -> bool:
        """Whether the method's phasors need the drive's electrical angle with every
        sample (a drive that reports it on the bus): the paper's magnitudes do not."""
        return self is Method.COHERENT


class MethodChoice(StrEnum):
    """What ``station analyze`` is asked for; AUTO prefers the phase-coherent estimator."""

    AUTO = "auto"
    PAPER = "paper"
    COHERENT = "coherent"


def offset_limit_mA(rated_current_mA: int) -> int:
    """The drive accepts offsets within ±rated/2 (ICD.md §2, 0x2100:01/02), in whole mA."""
    return rated_current_mA // 2


class Effect(StrEnum):
    """Physics beyond the paper's model, named as in CLI.md's vocabulary."""

    FLUX_HARMONICS = "flux_harmonics"
    DETENT_TORQUE = "detent_torque"
    RELUCTANCE_TORQUE = "reluctance_torque"
    LOAD_RESONANCE = "load_resonance"
    CURRENT_DISTORTION = "current_distortion"
    CURRENT_LOOP_LAG = "current_loop_lag"
    FRICTION = "friction"
    SENSOR_CLOCK_DRIFT = "sensor_clock_drift"
    # Appended, never inserted: a unit's concealed effects are drawn one per
    # member in this order, so existing serials keep the effects they had.
    MAGNETIC_SATURATION = "magnetic_saturation"
    ROTOR_ECCENTRICITY = "rotor_eccentricity"


class Axis(StrEnum):
    """Sensor axes as the recording metadata names them (ICD.md §5)."""

    X = "x"
    Y = "y"
    Z = "z"

    @property
    def column(self) -> int:
        """Position of the axis in the sensor's X, Y, Z sample."""
        return "xyz".index(self.value)


class LoadKind(StrEnum):
    """The mechanical loads of the paper: a disk on the shaft, or the belt pan unit."""

    DISK = "disk"
    BELT = "belt"


@dataclass(frozen=True)
class Trims:
    """The drive's four current trims (ICD.md §2, object 0x2100).

    Floats, because estimates are; the drive stores integers (see ``rounded``).
    """

    offset_a_mA: float = 0.0
    offset_b_mA: float = 0.0
    gain_a: float = float(GAIN_UNITY)
    gain_b: float = float(GAIN_UNITY)

    def rounded(self) -> Trims:
        return Trims(
            float(round(self.offset_a_mA)),
            float(round(self.offset_b_mA)),
            float(round(self.gain_a)),
            float(round(self.gain_b)),
        )

    def integers(self) -> tuple[int, int, int, int]:
        """As the drive stores them: whole numbers, in 0x2100's order (offsets A, B, gains A, B)."""
        t = self.rounded()
        return int(t.offset_a_mA), int(t.offset_b_mA), int(t.gain_a), int(t.gain_b)

    def as_dict(self) -> dict[str, float]:
        """The JSON object CLI.md prescribes for trims."""
        return {k: float(v) for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, data: dict[str, float]) -> Trims:
        return cls(
            float(data["offset_a_mA"]),
            float(data["offset_b_mA"]),
            float(data["gain_a"]),
            float(data["gain_b"]),
        )


NOMINAL_TRIMS = Trims()
