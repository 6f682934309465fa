"""The command line starts light: help and rejections never wait for heavy stacks.

Timing is ``bench/run cli_start``'s job (a test never depends on how fast the
machine is); what a test can hold is which modules a command imports before
it answers.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

HEAVY = ("scipy", "matplotlib", "can", "canopen", "asammdf", "pymodbus", "psycopg", "numba",
         "station.service", "station.procedure", "station.benches", "station.analysis.pipeline",
         "station.sim")
"""The analysis, the bus and log-format stacks, the database drivers and the simulator."""

_PROBE = """
import json, sys
sys.argv = ["station", *json.loads(sys.argv[1])]
import station.cli
try:
    station.cli.main()
except SystemExit as stop:
    code = stop.code
print(json.dumps({"code": code, "loaded": sorted(m for m in HEAVY if m in sys.modules)}))
"""


def _loaded(args: list[str], home: Path) -> tuple[int, list[str]]:
    probe = f"HEAVY = {list(HEAVY)!r}\n" + _PROBE
    done = subprocess.run([sys.executable, "-c", probe, json.dumps(args)],
                          capture_output=True, text=True, check=False,
                          env={**os.environ, "STATION_HOME": str(home)})
    assert done.stdout.strip(), done.stderr
    last = done.stdout.strip().splitlines()[-1]
    result = json.loads(last)
    return int(result["code"] or 0), result["loaded"]


@pytest.mark.parametrize("args, code", [
    (["--help"], 0),
    (["calibrate", "--help"], 0),
    (["calibrate", "SN01"], 2),
    (["calibrate", "SN123", "--recipe", "no-such-recipe"], 2),
    (["calibrate", "SN123", "--bench", "no-such-bench.toml"], 2),
    (["recalibrate", "SN123"], 2),
    (["analyze", "no-such-recording.blf"], 2),
    (["diagnose", "no-such-recording.blf"], 2),
    (["sim", "record", "x.blf", "--serial", "SN1", "--schedule", "calibration", "--effect",
      "no_such_effect"], 2),
    (["query", "--since", "yesterday"], 2),
    (["stats", "--json", "--format", "csv"], 2),
    (["history", "SN999"], 0),
    (["report", "SN999"], 2),
])
def test_help_and_rejections_answer_before_the_heavy_stacks_load(
    args: list[str], code: int, tmp_path: Path,
) -> None:
    answered, loaded = _loaded(args, tmp_path)
    assert answered == code
    assert loaded == []


def test_the_probe_sees_a_command_that_does_load_them(tmp_path: Path) -> None:
    recording = tmp_path / "x.blf"
    answered, loaded = _loaded(["sim", "record", str(recording), "--serial", "SN1",
                                "--schedule", "calibration", "--json"], tmp_path)
    assert answered == 0 and "station.sim" in loaded and "can" in loaded
