"""The import layers of ``pyproject.toml`` hold, and the drivers' contract names every
station module but the shared core (a module added later is forbidden by default)."""

from __future__ import annotations

import pkgutil
import subprocess
import sys
import tomllib
from pathlib import Path
from typing import Any

import station

ROOT = Path(__file__).resolve().parents[1]
SHARED_CORE = {"station.core", "station.errors", "station.cia301"}


def _contracts() -> dict[str, dict[str, Any]]:
    config = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    contracts = config["tool"]["importlinter"]["contracts"]
    return {c["id"]: c for c in contracts}


def test_every_layer_contract_is_kept() -> None:
    linter = Path(sys.executable).with_name("lint-imports")
    done = subprocess.run([str(linter), "--config", str(ROOT / "pyproject.toml")],
                          cwd=ROOT, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stdout[-4000:] + done.stderr[-2000:]
    assert "4 kept, 0 broken" in done.stdout


def test_drivers_may_import_only_the_shared_core_of_the_station() -> None:
    modules = {f"station.{m.name}" for m in pkgutil.iter_modules(station.__path__)}
    forbidden = set(_contracts()["drivers"]["forbidden_modules"])
    assert modules >= SHARED_CORE
    assert forbidden == modules - SHARED_CORE


def test_the_shared_core_imports_nothing_but_itself() -> None:
    """What the drivers may import must not lead them back into the station."""
    code = ("import sys; import station.core, station.errors, station.cia301; "
            "print(sorted(m for m in sys.modules if m.startswith(('station', 'drivers', "
            "'can', 'canopen', 'pymodbus', 'numpy'))))")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, check=True)
    assert done.stdout.strip() == repr(sorted(SHARED_CORE | {"station"}))


def test_the_runtime_opens_a_simulated_bench_without_importing_the_simulator_first() -> None:
    code = ("import sys; import station.service, station.procedure, station.benches; "
            "print(any(m.startswith('station.sim.') for m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True,
                          text=True, check=True)
    assert done.stdout.strip() == "False"
