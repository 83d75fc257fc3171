"""Reading an HTML report without a browser: the data its page draws.

The page carries the report's values as JSON in ``script#whiztap-data`` and
draws them with its own script (tests/test_report_browser.py drives that in
Chromium); these helpers let the other tests check what a page holds."""

from __future__ import annotations

import json
import re
from typing import Any

_DATA = re.compile(r"<script type='application/json' id='whiztap-data'>(.*?)</script>", re.S)


def page_data(page: str) -> dict[str, Any]:
    """The JSON a report page embeds (one script element, closed only by its own end tag)."""
    [found] = _DATA.findall(page)
    return json.loads(found)


def sections(data: dict[str, Any]) -> dict[str, dict[str, Any]]:
    """Every section and subsection by id."""
    out: dict[str, dict[str, Any]] = {}

    def walk(items: list[dict[str, Any]]) -> None:
        for s in items:
            out[s["id"]] = s
            walk(s.get("sections") or [])

    walk(data["sections"])
    return out


def table_rows(section: dict[str, Any]) -> list[dict[str, Any]]:
    """A section's table as {column label: cell} rows."""
    table = section["table"]
    labels = [c["label"] for c in table["columns"]]
    return [dict(zip(labels, r["c"])) for r in table["rows"]]
