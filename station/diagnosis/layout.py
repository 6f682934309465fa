"""The model's parameters as named blocks, and which model a diagnosis fits.

Below the model and every effect's module: an effect declares its parameters as blocks
(``station.diagnosis.effects``), the model lays them out in one flat vector, and the fit
solves each block the way its kind says.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from station.core import Effect


class ChainKind(StrEnum):
    """The mechanics between rotor and sensor that the recording's fixture declares."""

    RIGID = "rigid"  # sensor on a disk on the shaft (gear ratio 1)
    BELT = "belt"  # sensor on a load driven through a belt (gear ratio ≠ 1)


class BlockKind(StrEnum):
    LINEAR = "linear"  # solved by least squares at every start: the error is (nearly) linear
    ANGLES = "angles"  # one per condition, each touching only its condition's rows
    NONLINEAR = "nonlinear"


@dataclass(frozen=True)
class Block:
    """A named run of parameters: where it sits, start values, bounds, how it is solved."""

    name: str
    size: int
    start: float | tuple[float, ...]
    low: float = -np.inf
    high: float = np.inf
    kind: BlockKind = BlockKind.NONLINEAR
    rejects: tuple[int, ...] = ()
    """Bounds (−1 low, +1 high) a fit may not rest on and still be the group's physics:
    a clock 5000 ppm off or a current loop twenty periods late is something else the
    group stands in for. (Friction's smoothing has none: its ceiling is still Coulomb
    friction, ``FRICTION_SMOOTHING_MAX``.)"""
    null_band: float = 0.0
    """Values nearer zero than this leave no physics of the group's own: a clock keeping
    SYNC's rate to a few ppm is the sensor's constant delay, and a fit that ends there
    holds a fixed sub-sample phase that stands in for something else (``MIN_CLOCK_PPM``)."""


@dataclass
class Layout:
    """Where each named block sits in the flat parameter vector."""

    blocks: list[Block] = field(default_factory=list)
    slices: dict[str, slice] = field(default_factory=dict)

    def add(self, block: Block) -> None:
        begin = self.size
        self.blocks.append(block)
        self.slices[block.name] = slice(begin, begin + block.size)

    @property
    def size(self) -> int:
        return sum(b.size for b in self.blocks)

    def has(self, name: str) -> bool:
        return name in self.slices

    def block(self, name: str) -> Block:
        return next(b for b in self.blocks if b.name == name)

    def start(self) -> NDArray[np.float64]:
        out = np.empty(self.size)
        for b in self.blocks:
            out[self.slices[b.name]] = b.start
        return out

    def bounds(self) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        low = np.empty(self.size)
        high = np.empty(self.size)
        for b in self.blocks:
            low[self.slices[b.name]] = b.low
            high[self.slices[b.name]] = b.high
        return low, high

    def indices(self, kind: BlockKind) -> NDArray[np.intp]:
        parts = [np.arange(self.slices[b.name].start, self.slices[b.name].stop)
                 for b in self.blocks if b.kind is kind]
        return np.concatenate(parts) if parts else np.zeros(0, dtype=np.intp)


@dataclass(frozen=True)
class ModelSpec:
    """Which chain, which term groups, and the sensor clock's form when it drifts."""

    chain: ChainKind
    effects: frozenset[Effect] = frozenset()
    clock_wraps: bool = True  # a drifting sensor holds its latest sample for each SYNC
    # Whether each segment's mean torque must balance its drag. Without it the load angles
    # are free nuisances: a start that nothing unmodelled can bend.
    dc_balance: bool = True
    # The sensor's transfer bends (a + c2·a²/FS + c3·a³/FS²): physics no id describes,
    # modelled so that it can be told from the ids it would otherwise be taken for.
    sensor_bend: bool = False

    def with_effect(self, effect: Effect) -> ModelSpec:
        return replace(self, effects=self.effects | {effect})

    def without(self, effect: Effect) -> ModelSpec:
        return replace(self, effects=self.effects - {effect})

    def label(self) -> str:
        named = " + ".join(sorted(e.value for e in self.effects)) or "nominal"
        return named + (" + sensor bend (no id)" if self.sensor_bend else "")


def chain_for(gear_ratio: float) -> ChainKind:
    return ChainKind.RIGID if abs(gear_ratio - 1.0) < 1e-9 else ChainKind.BELT

