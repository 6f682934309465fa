"""The pieces every station report page is made of: one self-contained HTML file.

Reports are archived with the unit's records and opened years later, on a
laptop or on a phone at the line, so a page has no script and no external
resource: figures are inline SVG with their text kept as text. Figures are
drawn on ``matplotlib.figure.Figure`` objects, never through pyplot, which
keeps every figure in a global registry and picks a GUI backend.

matplotlib is imported by the functions that draw, not by this module: the
command line imports the report modules only for the commands that write one.
"""

from __future__ import annotations

import html
import io
import math
from collections.abc import Sequence
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from matplotlib.figure import Figure

STYLE = """
body { font-family: system-ui, sans-serif; max-width: 1100px; margin: 2em auto;
       padding: 0 1em; color: #222; line-height: 1.45; }
h1 { font-size: 1.5em; margin-bottom: 0.2em; overflow-wrap: anywhere; }
h2 { font-size: 1.2em; margin-top: 2em; border-bottom: 1px solid #ccc; }
.scroll { overflow-x: auto; max-width: 100%; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #ccc; padding: 0.25em 0.6em; vertical-align: top; text-align: left; }
th { background: #f2f2f2; }
td.num { text-align: right; font-variant-numeric: tabular-nums; white-space: nowrap; }
td.path, span.path { overflow-wrap: anywhere; font-family: ui-monospace, monospace;
                     font-size: 0.95em; }
table.inner td { border: none; padding: 0.05em 0.5em 0.05em 0; }
table.inner td.num { white-space: normal; overflow-wrap: anywhere; }
tr.chosen td { background: #e8f6ec; font-weight: 600; }
tr.round td { background: #f7f7f7; font-weight: 600; }
tr.failed td, tr.implausible td { background: #fdecea; }
p.verdict { font-size: 1.1em; }
.mismatch, .fail { color: #a93226; font-weight: 700; }
.match, .pass { color: #1e8449; font-weight: 700; }
.caution { color: #9a6700; font-weight: 600; }
.note { color: #555; font-size: 0.9em; overflow-wrap: anywhere; }
.banner { padding: 0.6em 1em; border-radius: 4px; margin: 1em 0; font-size: 1.05em; }
.banner.v-pass { background: #e8f6ec; border: 1px solid #1e8449; }
.banner.v-fail, .banner.v-error, .banner.v-aborted, .banner.v-open {
    background: #fdecea; border: 1px solid #a93226; }
.figures { display: flex; flex-wrap: wrap; gap: 0.5em 1.5em; }
.figures figure { flex: 1 1 320px; max-width: 520px; }
figure { margin: 1em 0; }
figure svg { max-width: 100%; height: auto; }
figcaption { color: #444; font-size: 0.9em; }
"""
"""Shared by every page; narrow screens scroll wide tables inside their box, never the page."""


def escape(text: object) -> str:
    return html.escape(str(text), quote=True)


def num(value: Any, digits: int = 4) -> str:
    """Numbers to the precision a fit supports (a few significant digits), never more."""
    if isinstance(value, bool) or value is None:
        return "—" if value is None else str(value)
    if isinstance(value, int | np.integer):
        return str(int(value))
    if not isinstance(value, float | np.floating):
        return str(value)
    x = float(value)
    if not math.isfinite(x):
        return "—"
    if x == 0.0:
        return "0"
    if abs(x) >= 1e6 or abs(x) < 1e-3:
        return f"{x:.{digits - 1}e}"
    decimals = max(0, digits - 1 - math.floor(math.log10(abs(x))))
    return f"{x:.{decimals}f}"


def table(header: Sequence[str], rows: Sequence[str]) -> str:
    """A table in a box that scrolls sideways on a narrow screen instead of the page."""
    head = "".join(f"<th>{escape(h)}</th>" for h in header)
    return (f"<div class='scroll'><table><thead><tr>{head}</tr></thead>"
            f"<tbody>{''.join(rows)}</tbody></table></div>")


def key_values(rows: Sequence[tuple[str, str]]) -> str:
    """A two-column table of named values; values are already HTML."""
    body = "".join(f"<tr><th scope='row'>{escape(k)}</th><td>{v}</td></tr>" for k, v in rows)
    return f"<div class='scroll'><table><tbody>{body}</tbody></table></div>"


def cells(*items: str, numeric: Sequence[int] = (), css: str = "") -> str:
    """One row; cells are already HTML (escaped by the caller)."""
    out = "".join(
        f"<td class='num'>{c}</td>" if i in numeric else f"<td>{c}</td>"
        for i, c in enumerate(items)
    )
    return f"<tr class='{css}'>{out}</tr>" if css else f"<tr>{out}</tr>"


def svg(fig: Figure, salt: str) -> str:
    """The figure as an inline <svg> element.

    Text stays text (searchable, small); the hash salt keeps the clip-path ids
    of different figures on one page from colliding.
    """
    from matplotlib import rc_context  # noqa: PLC0415 - only pages with figures draw

    buf = io.StringIO()
    with rc_context({"svg.fonttype": "none", "svg.hashsalt": salt}):
        fig.savefig(buf, format="svg", metadata={"Date": None})
    text = buf.getvalue()
    return text[text.index("<svg"):]


def figure(drawing: str, caption: str) -> str:
    return f"<figure>{drawing}<figcaption>{escape(caption)}</figcaption></figure>"


def page(title: str, body: Sequence[str]) -> str:
    """A whole page: viewport set so a phone shows it at its own width, not zoomed out."""
    head = ("<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
            "<meta name='viewport' content='width=device-width, initial-scale=1'>"
            f"<title>{escape(title)}</title><style>{STYLE}</style></head><body>")
    return "\n".join([head, *body, "</body></html>\n"])
