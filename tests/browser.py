"""A page as a person sees it: Debian's chromium, headless, at a given window width.

The report pages carry no script; the probe that measures them is added to a
copy, never to the page under test.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

RENDER_TIMEOUT_S = 120
"""Generous: chromium's first start on a loaded 2-core machine takes seconds, and a
timeout here would say nothing about the page."""

_PROBE = ("<script>document.body.setAttribute('data-overflow', String("
          "document.documentElement.scrollWidth - window.innerWidth));</script>")


def chromium_binary() -> str | None:
    for name in ("chromium", "chromium-browser", "google-chrome"):
        found = shutil.which(name)
        if found:
            return found
    return None


def _run(binary: str, width: int, height: int, *args: str) -> str:
    done = subprocess.run(
        [binary, "--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars",
         f"--window-size={width},{height}", *args],
        capture_output=True, text=True, timeout=RENDER_TIMEOUT_S, check=True)
    return done.stdout


def screenshot(binary: str, page: Path, width: int, out: Path, height: int = 3000) -> Path:
    _run(binary, width, height, f"--screenshot={out}", page.resolve().as_uri())
    return out


def overflow_px(binary: str, page: Path, width: int) -> int:
    """How far the page is wider than a window ``width`` pixels wide (0: it fits)."""
    probe = page.with_name(page.stem + ".probe.html")
    probe.write_text(page.read_text(encoding="utf-8").replace("</body>", _PROBE + "</body>"),
                     encoding="utf-8")
    dom = _run(binary, width, 2000, "--dump-dom", probe.resolve().as_uri())
    found = re.search(r'data-overflow="(-?\d+)"', dom)
    assert found is not None, "the probe did not run"
    return int(found.group(1))
