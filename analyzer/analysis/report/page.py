"""One self-contained, interactive HTML page: the shell every HTML report
(``analyze``, ``probe``, ``fuzz``) is written into.

The page carries its data as JSON (``script#whiztap-data``) and the code that
draws it: ``page-assets/report.js`` (sortable, filterable tables, the frame view)
and uPlot 1.6.32 (MIT, ``page-assets/uPlot.LICENSE``; the npm package's
``dist/uPlot.iife.min.js``, 51 KB) for the plots, all inline.  It works
offline and asks nothing of the network when it is viewed.  ``make
vendor-js`` fetches uPlot again from the npm registry and checks it.

The data is the report's own values, each shown as every output shows it
(``printable``: control characters escaped).  The JSON is ASCII and holds no
``<`` (written ``\\u003c``), so no value can end or change the script
element; the page's code puts every value in as text, never as markup.
"""

from __future__ import annotations

import html
import json
from functools import cache
from importlib import resources
from typing import Any

from whiztap.analyzer.analysis.frame_context import FrameRow
from whiztap.analyzer.protocol.text import printable

UPLOT_VERSION = "1.6.32"


@cache
def _asset(name: str) -> str:
    return (resources.files(__package__) / "page-assets" / name).read_text(encoding="utf-8")


def _json(data: dict[str, Any]) -> str:
    text = json.dumps(data, separators=(",", ":"))  # ASCII: no control character reaches the file raw
    return text.replace("<", "\\u003c")  # no tag, no comment ('<!--' would change how the element ends)


def page(title: str, data: dict[str, Any]) -> str:
    """The page for ``data`` (the shape ``page-assets/report.js`` draws: heading,
    verdict, lines, sections, frames)."""
    return "".join((
        "<!doctype html><html lang='en'><head><meta charset='utf-8'>",
        "<meta name='viewport' content='width=device-width,initial-scale=1'>",
        f"<meta name='generator' content='whiztap; uPlot {UPLOT_VERSION}'>",
        f"<title>{html.escape(title)}</title>",
        f"<style>{_asset('uPlot.min.css')}</style><style>{_asset('report.css')}</style></head>",
        "<body><main id='report'><noscript>This report draws its tables with JavaScript; "
        "the JSON report (--format json) has the same content.</noscript></main>",
        f"<script type='application/json' id='whiztap-data'>{_json(data)}</script>",
        f"<script>{_asset('uPlot.iife.min.js')}</script>",
        f"<script>{_asset('report.js')}</script>",
        "</body></html>\n",
    ))


def column(key: str, label: str, kind: str = "text") -> dict[str, str]:
    """A table column: ``kind`` says how it shows and sorts (text, num, code,
    rule, sev, frames)."""
    return {"key": key, "label": label, "kind": kind}


def row(cells: list[Any], frames: str | None = None, hit: int = -1, anchor: str | None = None) -> dict[str, Any]:
    """A table row; ``frames``: the key of its frame view, ``hit`` the item
    it is about there (-1: the whole view)."""
    r: dict[str, Any] = {"c": [printable(c) if isinstance(c, str) else c for c in cells]}
    if frames is not None:
        r["f"], r["h"] = frames, hit
    if anchor is not None:
        r["id"] = anchor
    return r


def table(table_id: str, columns: list[dict[str, str]], rows: list[dict[str, Any]],
          filters: tuple[str, ...] = ()) -> dict[str, Any]:
    """A sortable table, with a select per column named in ``filters`` and a text filter."""
    return {"id": table_id, "columns": columns, "rows": rows, "filters": list(filters)}


def text(words: str, css: str | None = None) -> dict[str, Any]:
    """A paragraph, its characters shown as every output shows them (``printable``)."""
    return {"text": printable(words), "class": css} if css else {"text": printable(words)}


def frame_view(title: str, rows: list[FrameRow], start: int | None = None) -> dict[str, Any]:
    """One connection's frames for the page's frame view, times from ``start``
    (by default its first item's)."""
    if start is None:
        start = rows[0].t_ns if rows else 0
    return {"title": printable(title), "rows": [
        {"i": r.index, "t": round((r.t_ns - start) / 1e9, 6), "dir": r.direction, "kind": r.kind, "text": r.text,
         "hex": r.hex, "size": r.size, "meaning": printable(r.meaning), "section": r.section, "rules": list(r.rules)}
        for r in rows]}
