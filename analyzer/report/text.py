"""The report for people: a terminal rendering (rich) and Markdown."""

from __future__ import annotations

from typing import Any

from rich.console import Console
from rich.table import Table
from rich.text import Text

from analyzer.text import shorten

_STYLE = {"error": "bold red", "warning": "yellow", "info": "cyan"}
TEXT_FRAME = 160  # characters of a frame in the text report; longer ones end in …
MD_FRAME = 120  # characters of a frame in a Markdown table; longer ones end in … (the JSON has them whole)


def duration(ns: int | float) -> str:
    if ns >= 1_000_000_000:
        return f"{ns / 1e9:.2f} s"
    if ns >= 1_000_000:
        return f"{ns / 1e6:.2f} ms"
    if ns >= 1_000:
        return f"{ns / 1e3:.1f} µs"
    return f"{ns:.0f} ns"


def channel_ranges(channel_map: dict[str, dict[str, int]]) -> str:
    """'servo 0-5, switch 6-11, sensor 12-23': runs of channels with one unit type."""
    names = {0: "servo", 1: "switch", 2: "sensor"}
    runs: list[list] = []  # [unit, first, last]
    for ch, cfg in sorted(((int(k), v) for k, v in channel_map.items())):
        unit = names.get(cfg["unit_type"], f"type {cfg['unit_type']}")
        if runs and runs[-1][0] == unit and runs[-1][2] == ch - 1:
            runs[-1][2] = ch
        else:
            runs.append([unit, ch, ch])
    return ", ".join(f"{u} {a}" if a == b else f"{u} {a}-{b}" for u, a, b in runs)


def headline(report: dict[str, Any]) -> str:
    s = report["summary"]
    files = len(report["files"])
    return (f"{files} file{'s' * (files != 1)}, {s['connections']} connection{'s' * (s['connections'] != 1)}, "
            f"{s['frames']:,} items over {s['duration_s']:.1f} s")


def verdict(report: dict[str, Any]) -> str:
    sev = report["summary"]["violations_by_severity"]
    counts = f"{sev['error']} errors, {sev['warning']} warnings, {sev['info']} info"
    if report["passed"]:
        text = f"PASS: no violation at or above {report['severity_threshold']} ({counts})"
    else:
        text = f"FAIL: violations at or above {report['severity_threshold']} ({counts})"
    if report.get("nothing_judged"):
        allowed = " (allowed by --allow-empty)" if report["passed"] else ""
        text = f"NOTHING TO JUDGE: {report['nothing_judged']}{allowed}"
    unreadable = len(report.get("unreadable", ()))
    if unreadable:
        text = f"INCOMPLETE: {unreadable} input{'s' * (unreadable != 1)} could not be read. {text}"
    return text


def render_text(report: dict[str, Any], console: Console) -> None:
    rule = report["checksum_rule"]
    console.print(Text("whiztap conformance report", style="bold"), f"— {headline(report)}")
    console.print(f"Spec Rev {report['spec_revision']}; checksum rule: {rule['name']} ({rule['description']})")
    if report["ignored_rules"]:
        console.print(f"Ignored rules: {', '.join(report['ignored_rules'])}")

    if len(report["per_file"]) > 1:
        table = Table(title="Files", title_justify="left", box=None, header_style="bold")
        for col in ("file", "connections", "frames", "violations"):
            table.add_column(col, justify="left" if col == "file" else "right", overflow="fold")
        for row in report["per_file"]:
            table.add_row(row["file"], str(row["connections"]), f"{row['frames']:,}", str(row["violations"]))
        console.print(table)

    table = Table(title="Connections", title_justify="left", box=None, header_style="bold")
    for col, justify in (("conn", "right"), ("client", "left"), ("mode", "left"), ("handshake", "left"),
                         ("items", "right"), ("violations", "right")):
        table.add_column(col, justify=justify, overflow="fold")
    for c in report["connections"]:
        table.add_row(str(c["conn"]), c["client"] or "-", c["mode"], c["handshake"], f"{c['frames']:,}",
                      str(sum(c["violations"].values())))
    console.print(table)
    for c in report["connections"]:
        for note in c["notes"]:
            console.print(f"  conn {c['conn']}: {note}")
        if c["channel_map"]:
            console.print(f"  conn {c['conn']} channels: {channel_ranges(c['channel_map'])}", overflow="fold")

    kinds = report["summary"]["frames_by_kind"]
    table = Table(title="Items by kind", title_justify="left", box=None, header_style="bold")
    table.add_column("kind")
    table.add_column("client→server", justify="right")
    table.add_column("server→client", justify="right")
    for kind in sorted(set(kinds["c2s"]) | set(kinds["s2c"])):
        table.add_row(kind, f"{kinds['c2s'].get(kind, 0):,}", f"{kinds['s2c'].get(kind, 0):,}")
    console.print(table)

    if report["violations"]:
        console.print(Text("Violations", style="bold"))
        for v in report["violations"]:
            style = _STYLE[v["severity"]]
            line = Text()
            line.append(f"{v['rule_id']} ", style=style)
            line.append(f"[{v['severity']}] conn {v['conn']} {v['dir'] or ''} +{v['t_rel_s']:.3f}s  ")
            line.append(v["detail"])
            console.print(line)
            frame = shorten(v["frame"], TEXT_FRAME)
            console.print(Text(f"    {frame}", style="dim"), f"  ({v['section']})", overflow="fold")
        if report["violations_not_listed"]:
            console.print(f"… and {report['violations_not_listed']} more not listed")
        counts = Table(title="Violations by rule", title_justify="left", box=None, header_style="bold")
        counts.add_column("rule")
        counts.add_column("count", justify="right")
        for rule_id, n in report["rule_counts"].items():
            counts.add_row(rule_id, str(n))
        console.print(counts)

    if report["latency"]:
        table = Table(title="Latency by request", title_justify="left", box=None, header_style="bold")
        for col in ("request", "count", "p50", "p95", "p99", "max"):
            table.add_column(col, justify="left" if col == "request" else "right")
        for row in report["latency"]:
            table.add_row(row["request"], f"{row['count']:,}", duration(row["p50_ns"]), duration(row["p95_ns"]),
                          duration(row["p99_ns"]), duration(row["max_ns"]))
        console.print(table)
    for title, n in report["unanswered"].items():
        console.print(f"Never answered: {n} × {title}", style="yellow")

    for c in report["set_configurations"]:
        ok = "ok" if c["ok"] else f"expected {c['expected']}"
        fits = ", ".join(c["satisfies"]) or "no candidate rule"
        console.print(f"Set Configuration conn {c['conn']}: checksum {c['checksum']} ({ok}); fits: {fits}")

    if report.get("unreadable"):
        console.print(Text("Not in this report (could not be read)", style="bold red"))
        for u in report["unreadable"]:
            console.print(f"  {u['error']}", overflow="fold")
    good = report["passed"] and not report.get("unreadable")
    console.print(Text(verdict(report), style="bold green" if good else "bold red"))


def render_markdown(report: dict[str, Any]) -> str:
    rule = report["checksum_rule"]
    out = [
        "# whiztap conformance report",
        "",
        f"{headline(report)}. Spec Rev {report['spec_revision']}; checksum rule `{rule['name']}` "
        f"({rule['description']}).",
        "",
        f"**{verdict(report)}**",
        "",
        "## Connections",
        "",
        "| file | conn | client | mode | handshake | items | violations |",
        "|---|---:|---|---|---|---:|---:|",
    ]
    for c in report["connections"]:
        out.append(f"| {c['file']} | {c['conn']} | {c['client'] or '-'} | {c['mode']} | {c['handshake']} | "
                   f"{c['frames']} | {sum(c['violations'].values())} |")
    out += ["", "## Violations", ""]
    if report["violations"]:
        out += ["| rule | severity | conn | t (s) | frame | detail |", "|---|---|---:|---:|---|---|"]
        for v in report["violations"]:
            frame = shorten(v["frame"], MD_FRAME)
            frame = frame.replace("|", "\\|").replace("`", "'")
            out.append(f"| `{v['rule_id']}` | {v['severity']} | {v['conn']} | {v['t_rel_s']:.3f} | "
                       f"`{frame}` | {v['detail'].replace('|', '/')} |")
        if report["violations_not_listed"]:
            out.append(f"\n… and {report['violations_not_listed']} more not listed.")
    else:
        out.append("None.")
    if report["latency"]:
        out += ["", "## Latency", "", "| request | count | p50 | p95 | p99 | max |", "|---|---:|---:|---:|---:|---:|"]
        for row in report["latency"]:
            out.append(f"| {row['request']} | {row['count']} | {duration(row['p50_ns'])} | "
                       f"{duration(row['p95_ns'])} | {duration(row['p99_ns'])} | {duration(row['max_ns'])} |")
    if report["unanswered"]:
        out += ["", "Never answered: " + ", ".join(f"{n} × {t}" for t, n in report["unanswered"].items())]
    if report["set_configurations"]:
        out += ["", "## Set Configuration checksums", "", "| conn | checksum | expected | fits |",
                "|---:|---:|---:|---|"]
        for c in report["set_configurations"]:
            out.append(f"| {c['conn']} | {c['checksum']} | {c['expected']} | {', '.join(c['satisfies']) or '-'} |")
    if report.get("unreadable"):
        out += ["", "## Not in this report (could not be read)", ""]
        out += [f"- {u['error']}" for u in report["unreadable"]]
    return "\n".join(out) + "\n"
