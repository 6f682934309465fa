"""How long the whole test suite takes, as CI runs it (issue 19: 8 minutes on this machine).

The suite runs as a whole process, as a developer or CI waits for it: pytest with the
project's own options (every core, slow tests included). Beside its wall time go the CPU
seconds it and every process under it spent: that is what must fit in the cores times
the target, however the tests are spread, so it says how much work has to go before the
wall time can meet the target. The tests must also pass: a fast suite that fails is
no figure at all.
"""

from __future__ import annotations

import os
import resource
import subprocess
import sys
import tempfile
import time
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path

from bench.record import BenchRecord, Goal

TARGET_S = 480.0
ROOT = Path(__file__).resolve().parents[1]


def _children_cpu_s() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _not_passed(junit: Path) -> int:
    """Failures and errors as the run's JUnit report counts them (every suite's)."""
    root = ET.parse(junit).getroot()
    suites = [root] if root.tag == "testsuite" else list(root.iter("testsuite"))
    return sum(int(s.get("failures", 0)) + int(s.get("errors", 0)) for s in suites)


def measure() -> Iterator[BenchRecord]:
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    with tempfile.TemporaryDirectory(prefix="station-suite-") as tmp:
        junit = Path(tmp) / "junit.xml"
        cpu_before = _children_cpu_s()
        started = time.perf_counter()
        done = subprocess.run(
            [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider",
             f"--junitxml={junit}"],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, check=False,
        )
        wall = time.perf_counter() - started
        cpu = _children_cpu_s() - cpu_before
        # Without a report nothing can be counted: at least one did not pass.
        counted = _not_passed(junit) if junit.is_file() else 1
    # pytest's exit code and the report must agree that nothing failed (exit 0, none counted).
    not_passed = counted if done.returncode == 0 else max(counted, 1)
    yield BenchRecord("tests_wall", wall, "s", TARGET_S, Goal.AT_MOST)
    yield BenchRecord("tests_cpu", cpu, "s", TARGET_S * (cores or 1), Goal.AT_MOST)
    yield BenchRecord("tests_not_passed", not_passed, "tests", 0, Goal.AT_MOST)
