"""One self-contained HTML file: the report's tables and plots (inline SVG).

Plots are drawn with matplotlib (the ``html`` extra), imported only here.
Without it the report is written all the same, without plots, and says so.
"""

from __future__ import annotations

import html
import importlib
import io
from collections.abc import Callable
from types import ModuleType
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.analysis.facts import NS, Analysis
from whiztap.analyzer.analysis.report.text import duration, headline, verdict
from whiztap.analyzer.analysis.report.text import FLEET_COLUMNS, FLEET_DAY_COLUMNS, fleet_rows
from whiztap.analyzer.analysis.report.words import (
    assumed_words,
    CLIENT_LATENCY,
    EFFECTS_HEADING,
    SERVER_LATENCY,
    fleet_headings,
    fleet_key,
    group_name,
    intervention_lines,
    latency_tables,
    several_files,
    side_cell,
)
from whiztap.analyzer.protocol.text import plural, printable

if TYPE_CHECKING:
    from matplotlib.figure import Figure

_CSS = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:70em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.2em .5em;text-align:left;
vertical-align:top;overflow-wrap:anywhere}
th{background:#f3f3f3}.error{color:#b00}.warning{color:#a60}.info{color:#06a}.pass{color:#070}.fail{color:#b00}
code{font-size:90%;word-break:break-all}figure{margin:1em 0}
"""


NO_PLOTS = ("the HTML report has no plots: they are drawn with matplotlib, which is not installed "
            "(pip install 'whiztap[html]')")


def plots_missing() -> str | None:
    """Why the HTML report will have no plots (``NO_PLOTS``), or None when it will have them."""
    try:
        importlib.import_module("matplotlib")  # whether it can be imported is the question
    except ImportError:
        return NO_PLOTS
    return None


def _pyplot() -> ModuleType:
    import matplotlib

    matplotlib.use("Agg")
    # the same report twice is the same file: SVG ids from a fixed salt, no date in the metadata
    matplotlib.rcParams["svg.hashsalt"] = "whiztap"
    import matplotlib.pyplot as plt

    return plt


def _svg(fig: Figure) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight", metadata={"Date": None})
    text = buf.getvalue()
    return text[text.index("<svg"):]


def _plots(analysis: Analysis) -> list[tuple[str, str]]:
    plt = _pyplot()
    start = analysis.first_ns or 0
    plots: list[tuple[str, str]] = []
    kinds = sorted({k for c in analysis.frames_per_second.values() for k in c})
    if kinds:  # seconds that counted no item draw nothing: no plot, no legend without lines
        fig, ax = plt.subplots(figsize=(9, 3))
        seconds = sorted(analysis.frames_per_second)
        xs = [s - start / NS for s in seconds]
        for kind in kinds:
            ax.plot(xs, [analysis.frames_per_second[s].get(kind, 0) for s in seconds], label=kind, marker=".")
        ax.set_xlabel("seconds from start")
        ax.set_ylabel("items per second")
        ax.legend(fontsize="small", ncol=4)
        plots.append(("Items over time, by kind", _svg(fig)))
        plt.close(fig)
    both = bool(analysis.client_latencies)  # the proxy stood in the middle: the server's and the client's
    server_title = f"Response latency, {SERVER_LATENCY}" if both else "Response latency"
    for latencies, title in ((analysis.latencies, server_title),
                             (analysis.client_latencies, f"Response latency, {CLIENT_LATENCY}")):
        if latencies:
            plots.append((title, _latency_plot(plt, latencies)))
    for kind, label in (("sensor", "Sensor values"), ("servo", "Servo positions (data / 4)")):
        series = {ch: s for (k, ch), s in sorted(analysis.values.items()) if k == kind}
        if not series:
            continue
        fig, ax = plt.subplots(figsize=(9, 3))
        for ch, s in series.items():
            ax.plot([(t - start) / NS for t, _ in s.points], [v for _, v in s.points], label=f"ch {ch}")
        ax.set_xlabel("seconds from start")
        ax.set_ylabel(label.lower())
        ax.legend(fontsize="small", ncol=6)
        plots.append((f"{label} per channel", _svg(fig)))
        plt.close(fig)
    return plots


def _latency_plot(plt: ModuleType, latencies: dict) -> str:
    fig, ax = plt.subplots(figsize=(9, 3))
    for title, stats in sorted(latencies.items()):
        buckets = stats.histogram()
        ax.step([(lo + hi) / 2 / 1e6 for lo, hi, _ in buckets], [n for *_, n in buckets], where="mid", label=title)
    ax.set_xscale("log")
    ax.set_xlabel("latency (ms)")
    ax.set_ylabel("responses")
    ax.legend(fontsize="small")
    svg = _svg(fig)
    plt.close(fig)
    return svg


_TOP_RULES = 8  # rules drawn one by one in the fleet's bars; the rest are one "other rules" bar
_MAX_LABELS = 40  # tick labels on a fleet plot's axis; more are thinned out


def _fleet_plots(table: dict[str, Any]) -> list[tuple[str, str]]:
    """A fleet table drawn: violations per group stacked by rule, and per group
    per day as a heat map (one row per group, one column per day)."""
    plt = _pyplot()
    groups = table["groups"]
    if not groups:
        return []
    names = [group_name(table, g) for g in groups]
    key = fleet_key(table)
    totals: dict[str, int] = {}
    for g in groups:
        for r in g["rules"]:
            totals[r["rule_id"]] = totals.get(r["rule_id"], 0) + r["count"]
    top = sorted(totals, key=lambda r: -totals[r])[:_TOP_RULES]
    height = min(0.3 * len(groups) + 1.2, 12)
    fig, ax = plt.subplots(figsize=(9, height))
    left = [0] * len(groups)
    for rule_id in top + ["other rules"]:
        counts = [sum(r["count"] for r in g["rules"] if (r["rule_id"] == rule_id) or
                      (rule_id == "other rules" and r["rule_id"] not in top)) for g in groups]
        if any(counts):
            ax.barh(range(len(groups)), counts, left=left, label=rule_id)
            left = [a + b for a, b in zip(left, counts)]
    _labels(ax.set_yticks, ax.set_yticklabels, names)
    ax.invert_yaxis()
    ax.set_xlabel("violations")
    if totals:
        ax.legend(fontsize="small", loc="upper left", bbox_to_anchor=(1.01, 1))  # beside the bars, never on them
    plots = [(f"Violations by {key}, by rule", _svg(fig))]
    plt.close(fig)
    days = sorted({d["day"] for g in groups for d in g["days"] if d["day"] is not None})
    if days:
        column = {day: i for i, day in enumerate(days)}
        grid = [[float("nan")] * len(days) for _ in groups]  # no recording that day: drawn grey
        for row, g in enumerate(groups):
            for d in g["days"]:
                if d["day"] is not None:
                    grid[row][column[d["day"]]] = d["violations"]
        fig, ax = plt.subplots(figsize=(9, height))
        colours = plt.get_cmap("Reds").copy()
        colours.set_bad("#dddddd")
        image = ax.imshow(grid, aspect="auto", cmap=colours, interpolation="nearest", vmin=0)
        fig.colorbar(image, ax=ax, label="violations")
        _labels(ax.set_yticks, ax.set_yticklabels, names)
        _labels(ax.set_xticks, ax.set_xticklabels, days, rotation=45)
        plots.append((f"Violations per day (UTC), by {key} (grey: no recording that day)", _svg(fig)))
        plt.close(fig)
    return plots


def _labels(set_ticks: Callable[..., object], set_labels: Callable[..., object], labels: list[str],
            **style: Any) -> None:
    """Tick labels on an axis, at most ``_MAX_LABELS`` of them, evenly spaced."""
    step = max(1, -(-len(labels) // _MAX_LABELS))
    ticks = list(range(0, len(labels), step))
    set_ticks(ticks)
    set_labels([labels[i] for i in ticks], fontsize="small", **style)


def _fleet(table: dict[str, Any], plotted: bool) -> list[str]:
    """A fleet table, its table by day and (``plotted``) its plots."""
    e = _escaped
    title, by_day = fleet_headings(table)
    groups, days = fleet_rows(table, _lines)
    key = fleet_key(table)
    parts = [f"<h2>{e(title)}</h2>", _table([key, *FLEET_COLUMNS], [[_cell(cell) for cell in row] for row in groups])]
    for caption, svg in _fleet_plots(table) if plotted else ():
        parts.append(f"<figure><figcaption><b>{e(caption)}</b></figcaption>{svg}</figure>")
    parts += [f"<h2>{e(by_day)}</h2>",
              _table([key, *FLEET_DAY_COLUMNS], [[_cell(cell) for cell in row] for row in days])]
    return parts


class _Markup(str):
    """HTML made here from escaped values: a cell taken as it is."""


def _lines(entries: list[str], empty: str) -> _Markup:
    """A cell of rules: one a line, so that a long list wraps between rules."""
    return _Markup("<br>".join(_escaped(entry) for entry in entries) or empty)


def _cell(value: object) -> str:
    return value if isinstance(value, _Markup) else _escaped(value)


def _table(headers: list[str], rows: list[list[str]]) -> str:
    head = "".join(f"<th>{_escaped(h)}</th>" for h in headers)
    body = "".join("<tr>" + "".join(f"<td>{cell}</td>" for cell in row) + "</tr>" for row in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def _escaped(value: object) -> str:
    """A value as HTML text: markup characters as entities (a frame may hold
    '<script>'), control characters shown escaped as in every other output."""
    return html.escape(printable(str(value)))


def _violations(report: dict[str, Any], violations: list[dict[str, Any]]) -> str:
    """A table of violations (or effects); with a side column when the proxy stood in the middle."""
    e = _escaped
    middle = "interventions" in report
    files = several_files(report)
    rows = []
    for v in violations:
        row = [f"<code>{e(v['rule_id'])}</code>", f"<span class='{e(v['severity'])}'>{e(v['severity'])}</span>",
               e(v["section"])] + ([e(v["file"])] if files else []) + [str(v["conn"])]
        if middle:
            row.append(e(side_cell(v)))
        rows.append(row + [f"{v['t_rel_s']:.3f}", f"<code>{e(v['frame'][:200])}</code>", e(v["detail"])])
    return _table(["rule", "severity", "section"] + (["file"] if files else []) + ["conn"]
                  + (["side"] if middle else []) + ["t (s)", "frame", "detail"], rows)


def _interventions(report: dict[str, Any]) -> list[str]:
    e = _escaped
    heading, rows = intervention_lines(report)
    parts = ["<h2>Interventions</h2>", f"<p>{e(heading)}.</p>"]
    if rows:
        parts.append(_table(["cause", "count", "actions"],
                            [[f"<code>{e(c)}</code>", str(n), e(a)] for c, n, a in rows]))
    section = report["interventions"]
    if section["effects"]:
        parts += [f"<p>{e(EFFECTS_HEADING)}:</p>", _violations(report, section["effects"])]
    if section["effects_not_listed"]:
        parts.append(f"<p>… and {plural(section['effects_not_listed'], 'more effect')} not listed.</p>")
    return parts


def render_html(report: dict[str, Any], analysis: Analysis) -> str:
    """Every value from the report goes through ``_escaped`` (numbers are formatted here)."""
    e = _escaped
    rule = report["checksum_rule"]
    parts = [
        f"<!doctype html><html><head><meta charset='utf-8'><title>whiztap report</title><style>{_CSS}</style>"
        "</head><body>",
        "<h1>whiztap conformance report</h1>",
        f"<p>{e(headline(report))}. Spec Rev {e(report['spec_revision'])}; checksum rule "
        f"<code>{e(rule['name'])}</code> ({e(rule['description'])}).</p>",
        f"<p class='{'pass' if report['passed'] else 'fail'}'><b>{e(verdict(report))}</b></p>",
    ]
    assumed = assumed_words(report)
    if assumed:
        parts.append(f"<p>{e(assumed)}.</p>")
    plotted = plots_missing() is None
    if not plotted:
        parts.append(f"<p class='warning'>{e(NO_PLOTS)}.</p>")
    for table in report.get("fleet", ()):
        parts += _fleet(table, plotted)
    parts += [
        "<h2>Connections</h2>",
        _table(["file", "conn", "client", "mode", "handshake", "items", "violations"],
               [[e(c["file"]), str(c["conn"]), e(c["client"] or "-"), e(c["mode"]), e(c["handshake"]),
                 str(c["frames"]), str(sum(c["violations"].values()))] for c in report["connections"]]),
    ]
    for title, svg in _plots(analysis) if plotted else ():
        parts.append(f"<figure><figcaption><b>{e(title)}</b></figcaption>{svg}</figure>")
    if "interventions" in report:
        parts += _interventions(report)
    parts.append("<h2>Violations</h2>")
    if report["violations"]:
        parts.append(_violations(report, report["violations"]))
        if report["violations_not_listed"]:
            parts.append(f"<p>… and {report['violations_not_listed']:,} more not listed.</p>")
    else:
        parts.append("<p>None.</p>")
    for label, rows in latency_tables(report):
        parts.append(f"<h2>Latency, {e(label)}</h2>" if label else "<h2>Latency</h2>")
        parts.append(_table(["request", "count", "p50", "p95", "p99", "max"],
                            [[e(r["request"]), str(r["count"]), duration(r["p50_ns"]), duration(r["p95_ns"]),
                              duration(r["p99_ns"]), duration(r["max_ns"])] for r in rows]))
    if report["unanswered"]:
        parts.append("<p>Never answered: " + e(", ".join(f"{n} × {t}" for t, n in report["unanswered"].items()))
                     + "</p>")
    if report["set_configurations"]:
        parts.append("<h2>Set Configuration checksums</h2>")
        files = several_files(report)
        parts.append(_table((["file"] if files else []) + ["conn", "checksum", "expected", "candidate rules it fits"],
                            [([e(c["file"])] if files else []) + [
                                str(c["conn"]), str(c["checksum"]), str(c["expected"]),
                                e(", ".join(c["satisfies"]) or "none")] for c in report["set_configurations"]]))
    if report.get("unreadable"):
        parts.append("<h2>Not in this report (could not be read)</h2><ul>")
        parts += [f"<li class='error'>{e(u['error'])}</li>" for u in report["unreadable"]]
        parts.append("</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)
