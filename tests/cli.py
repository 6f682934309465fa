"""The station's command line run in-process, as the tests of what people see use it."""

from __future__ import annotations

import json
import sys
from dataclasses import dataclass
from typing import Any

import pytest

from station.cli import main


@dataclass(frozen=True)
class Outcome:
    code: int
    stdout: str
    err: str  # stderr as printed

    @property
    def doc(self) -> Any:
        """stdout as the JSON document ``--json`` promises."""
        return json.loads(self.stdout)

    @property
    def stderr(self) -> str:
        """stderr with the console's wrapping undone: long messages read as one line."""
        return " ".join(self.err.split())


def run_cli(args: list[str], monkeypatch: pytest.MonkeyPatch,
            capsys: pytest.CaptureFixture[str]) -> Outcome:
    monkeypatch.setattr(sys, "argv", ["station", *args])
    with pytest.raises(SystemExit) as stop:
        main()
    captured = capsys.readouterr()
    code = stop.value.code
    return Outcome(code if isinstance(code, int) else 0 if code is None else 1,
                   captured.out, captured.err)
