"""Benchmark records and their printing."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from enum import StrEnum


class Goal(StrEnum):
    """Whether the value must reach the target from below or stay under it."""

    AT_LEAST = "at_least"
    AT_MOST = "at_most"


@dataclass(frozen=True)
class BenchRecord:
    name: str
    value: float
    unit: str
    target: float
    goal: Goal

    @property
    def ok(self) -> bool:
        if self.goal is Goal.AT_LEAST:
            return self.value >= self.target
        return self.value <= self.target

    def to_json(self) -> str:
        doc = asdict(self)
        doc.pop("goal")
        doc["value"] = round(self.value, 4)
        doc["ok"] = self.ok
        return json.dumps(doc)
