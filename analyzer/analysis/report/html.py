"""One self-contained HTML file: the report's tables and plots (inline SVG).

Plots are drawn with matplotlib (the ``html`` extra), imported only here.
"""

from __future__ import annotations

import html
import io
from typing import Any

from whiztap.analyzer.analysis.facts import NS, Analysis
from whiztap.analyzer.analysis.report.text import duration, headline, verdict
from whiztap.analyzer.analysis.report.words import EFFECTS_HEADING, intervention_lines
from whiztap.analyzer.protocol.text import printable

_CSS = """
body{font-family:system-ui,sans-serif;margin:2em;max-width:70em;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #ccc;padding:.2em .5em;text-align:left}
th{background:#f3f3f3}.error{color:#b00}.warning{color:#a60}.info{color:#06a}.pass{color:#070}.fail{color:#b00}
code{font-size:90%;word-break:break-all}figure{margin:1em 0}
"""


class MissingPlotLibrary(RuntimeError):
    pass


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise MissingPlotLibrary("the HTML report needs matplotlib: pip install 'whiztap[html]'") from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _svg(fig) -> str:
    buf = io.StringIO()
    fig.savefig(buf, format="svg", bbox_inches="tight")
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
    if analysis.latencies:
        fig, ax = plt.subplots(figsize=(9, 3))
        for title, stats in sorted(analysis.latencies.items()):
            buckets = stats.histogram()
            ax.step([(lo + hi) / 2 / 1e6 for lo, hi, _ in buckets], [n for *_, n in buckets], where="mid",
                    label=title)
        ax.set_xscale("log")
        ax.set_xlabel("latency (ms)")
        ax.set_ylabel("responses")
        ax.legend(fontsize="small")
        plots.append(("Response latency", _svg(fig)))
        plt.close(fig)
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
    rows = []
    for v in violations:
        row = [f"<code>{e(v['rule_id'])}</code>", f"<span class='{e(v['severity'])}'>{e(v['severity'])}</span>",
               e(v["section"]), str(v["conn"])]
        if middle:
            row.append(e(v.get("side") or f"seen by the {v['seen_by']}"))
        rows.append(row + [f"{v['t_rel_s']:.3f}", f"<code>{e(v['frame'][:200])}</code>", e(v["detail"])])
    return _table(["rule", "severity", "section", "conn"] + (["side"] if middle else []) + ["t (s)", "frame", "detail"],
                  rows)


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
        parts.append(f"<p>… and {section['effects_not_listed']} more effects not listed.</p>")
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
        "<h2>Connections</h2>",
        _table(["file", "conn", "client", "mode", "handshake", "items", "violations"],
               [[e(c["file"]), str(c["conn"]), e(c["client"] or "-"), e(c["mode"]), e(c["handshake"]),
                 str(c["frames"]), str(sum(c["violations"].values()))] for c in report["connections"]]),
    ]
    for title, svg in _plots(analysis):
        parts.append(f"<figure><figcaption><b>{e(title)}</b></figcaption>{svg}</figure>")
    if "interventions" in report:
        parts += _interventions(report)
    parts.append("<h2>Violations</h2>")
    if report["violations"]:
        parts.append(_violations(report, report["violations"]))
        if report["violations_not_listed"]:
            parts.append(f"<p>… and {report['violations_not_listed']} more not listed.</p>")
    else:
        parts.append("<p>None.</p>")
    if report["latency"]:
        parts.append("<h2>Latency</h2>")
        parts.append(_table(["request", "count", "p50", "p95", "p99", "max"],
                            [[e(r["request"]), str(r["count"]), duration(r["p50_ns"]), duration(r["p95_ns"]),
                              duration(r["p99_ns"]), duration(r["max_ns"])] for r in report["latency"]]))
    if report["unanswered"]:
        parts.append("<p>Never answered: " + e(", ".join(f"{n} × {t}" for t, n in report["unanswered"].items()))
                     + "</p>")
    if report["set_configurations"]:
        parts.append("<h2>Set Configuration checksums</h2>")
        parts.append(_table(["conn", "checksum", "expected", "candidate rules it fits"],
                            [[str(c["conn"]), str(c["checksum"]), str(c["expected"]),
                              e(", ".join(c["satisfies"]) or "none")] for c in report["set_configurations"]]))
    if report.get("unreadable"):
        parts.append("<h2>Not in this report (could not be read)</h2><ul>")
        parts += [f"<li class='error'>{e(u['error'])}</li>" for u in report["unreadable"]]
        parts.append("</ul>")
    parts.append("</body></html>")
    return "\n".join(parts)
