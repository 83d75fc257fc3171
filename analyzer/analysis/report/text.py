"""The report for people: a terminal rendering (rich) and Markdown."""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

from rich.console import Console, JustifyMethod
from rich.table import Table
from rich.text import Text

from whiztap.analyzer.analysis.report.words import (
    assumed_words,
    EFFECTS_HEADING,
    conn_words,
    fleet_headings,
    fleet_key,
    group_name,
    intervention_lines,
    latency_tables,
    rule_counts_each,
    rules_since_each,
    several_files,
    side_cell,
    side_words,
    verdict_words,
)
from whiztap.analyzer.protocol.text import plural, printable, shorten

_STYLE = {"error": "bold red", "warning": "yellow", "info": "cyan"}
TEXT_FRAME = 160  # characters of a frame in the text report; longer ones end in …
UNBOUNDED = 1_000_000  # a width no table reaches: to measure one's natural width
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
    return (f"{plural(len(report['files']), 'file')}, {plural(s['connections'], 'connection')}, "
            f"{plural(s['frames'], 'item')} over {s['duration_s']:.1f} s")


def verdict(report: dict[str, Any]) -> str:
    return verdict_words(report)


def _plain(console: Console, value: object, style: str = "") -> Text:
    """A value as Rich text: never read as markup or emoji codes (a frame may
    hold '[bold]'), its control characters shown escaped, never sent to the
    terminal; highlighted as Rich highlights plain strings."""
    text = console.render_str(printable(str(value)), markup=False, emoji=False)
    text.style = style  # under the highlights, as console.print(str, style=...) puts it
    return text


def _table(title: str, columns: list[tuple[str, JustifyMethod]], rows: list[list[object]],
           narrow: bool = False) -> Table:
    """A borderless table of plain cells (as ``_plain``, unhighlighted as
    Rich leaves table cells; a ``Text`` cell is taken as it is); columns:
    (name, justify).  ``narrow``: one space between columns, not two."""
    table = Table(title=title, title_justify="left", box=None, header_style="bold", collapse_padding=narrow,
                  pad_edge=not narrow)
    for name, justify in columns:
        table.add_column(name, justify=justify, overflow="fold")
    for row in rows:
        table.add_row(*(cell if isinstance(cell, Text) else Text(printable(str(cell))) for cell in row))
    return table


def render_text(report: dict[str, Any], console: Console) -> None:
    """Every value reaches the console as ``_plain`` text: values come from
    recordings and the wire, and the report is often read on a terminal."""
    rule = report["checksum_rule"]
    console.print(Text("whiztap conformance report", style="bold"), _plain(console, f"— {headline(report)}"))
    console.print(_plain(console, f"Spec Rev {report['spec_revision']}; checksum rule: {rule['name']} "
                                  f"({rule['description']})"))
    if report["ignored_rules"]:
        console.print(_plain(console, f"Ignored rules: {', '.join(report['ignored_rules'])}"))
    assumed = assumed_words(report)
    if assumed:
        console.print(_plain(console, assumed))
    for table in report.get("fleet", ()):
        _text_fleet(table, console)
    _text_traffic(report, console)
    if "interventions" in report:
        _text_interventions(report, console)
    if report["violations"]:
        _text_violations(report, console)
    _text_latency_and_checksums(report, console)
    if report.get("unreadable"):
        console.print(Text("Not in this report (could not be read)", style="bold red"))
        for u in report["unreadable"]:
            console.print(_plain(console, f"  {u['error']}"), overflow="fold")
    good = report["passed"] and not report.get("unreadable")
    console.print(Text(printable(verdict(report)), style="bold green" if good else "bold red"))


def _text_traffic(report: dict[str, Any], console: Console) -> None:
    """Files, connections (with their notes and channels) and items by kind."""
    if len(report["per_file"]) > 1:
        console.print(_table("Files", [("file", "left"), ("connections", "right"), ("frames", "right"),
                                       ("violations", "right")],
                             [[r["file"], r["connections"], f"{r['frames']:,}", r["violations"]]
                              for r in report["per_file"]]))

    files: list[tuple[str, JustifyMethod]] = [("file", "left")] if several_files(report) else []
    console.print(_table("Connections", files + [("conn", "right"), ("client", "left"), ("mode", "left"),
                                                 ("handshake", "left"), ("items", "right"), ("violations", "right")],
                         [([c["file"]] if files else []) + [
                             c["conn"], c["client"] or "-", c["mode"], c["handshake"], f"{c['frames']:,}",
                             sum(c["violations"].values())] for c in report["connections"]]))
    for c in report["connections"]:
        for note in c["notes"]:
            console.print(_plain(console, f"  {conn_words(report, c)}: {note}"))
        if c["channel_map"]:
            console.print(_plain(console, f"  {conn_words(report, c)} channels: {channel_ranges(c['channel_map'])}"),
                          overflow="fold")

    kinds = report["summary"]["frames_by_kind"]
    console.print(_table("Items by kind", [("kind", "left"), ("client→server", "right"),
                                           ("server→client", "right")],
                         [[kind, f"{kinds['c2s'].get(kind, 0):,}", f"{kinds['s2c'].get(kind, 0):,}"]
                          for kind in sorted(set(kinds["c2s"]) | set(kinds["s2c"]))]))


def _one_line(entries: list[str], empty: str) -> str:
    return ", ".join(entries) or empty


def fleet_rows(table: dict[str, Any], cell: Callable[[list[str], str], object] = _one_line,
               ) -> tuple[list[list[object]], list[list[object]]]:
    """A fleet table's rows (group, recordings, connections, items, violations,
    errors, warnings, verdict, rules since) and its rows by day (group, day,
    recordings, violations, rules), as every table-shaped format shows them;
    ``cell`` makes a cell of rules (and what a cell of none says) as the format wants it."""
    groups, days = [], []
    for g in table["groups"]:
        name, sev = group_name(table, g), g["violations_by_severity"]
        groups.append([name, g["recordings"], g["connections"], f"{g['frames']:,}", g["violations"], sev["error"],
                       sev["warning"], "pass" if g["passed"] else "FAIL", cell(rules_since_each(g), "none")])
        days += [[name, d["day"] or "unknown", d["recordings"], d["violations"],
                  cell(rule_counts_each(d["rule_counts"]), "-")] for d in g["days"]]
    return groups, days


def _one_a_line(entries: list[str], empty: str) -> Text:
    """A cell of rules for the terminal: one a line, so that it wraps between
    rules, never inside a rule's id."""
    return Text("\n".join(printable(e) for e in entries) or empty)


FLEET_COLUMNS = ["recordings", "connections", "items", "violations", "errors", "warnings", "verdict",
                 "rules broken (count, since)"]
FLEET_DAY_COLUMNS = ["day", "recordings", "violations", "rules"]


_NUMERIC = frozenset(("recordings", "connections", "items", "violations", "errors", "warnings"))


def _text_fleet(table: dict[str, Any], console: Console) -> None:
    """A fleet table and its table by day.  A group may have broken many
    rules: its cell lists them one a line, and when the table is wider than
    the terminal, the rules leave it for a table of their own (group, rules),
    which fits any width: a cell wraps between words, never inside a rule's
    id, and no column is squeezed to a few letters."""
    title, by_day = fleet_headings(table)
    groups, days = fleet_rows(table, _one_a_line)
    key = fleet_key(table)
    for heading, columns, rows in ((title, FLEET_COLUMNS, groups), (by_day, FLEET_DAY_COLUMNS, days)):
        layout: list[tuple[str, JustifyMethod]] = [(key, "left")]
        layout += [(c, "right" if c in _NUMERIC else "left") for c in columns]
        whole = _table(heading, layout, rows, narrow=True)
        if console.measure(whole, options=console.options.update_width(UNBOUNDED)).maximum <= console.width:
            console.print(whole)
            continue
        console.print(_table(heading, layout[:-1], [row[:-1] for row in rows], narrow=True))
        console.print(_table(f"{heading}: {columns[-1]}", [(key, "left"), (columns[-1], "left")],
                             [[row[0], row[-1]] for row in rows], narrow=True))


def _text_interventions(report: dict[str, Any], console: Console) -> None:
    heading, rows = intervention_lines(report)
    console.print(Text("Interventions", style="bold"))
    console.print(_plain(console, heading))
    if rows:
        console.print(_table("", [("cause", "left"), ("count", "right"), ("actions", "left")],
                             [list(row) for row in rows]))
    section = report["interventions"]
    if section["effects"]:
        console.print(Text(EFFECTS_HEADING, style="bold"))
        for v in section["effects"]:
            _text_violation(report, v, console)
    if section["effects_not_listed"]:
        console.print(_plain(console, f"… and {plural(section['effects_not_listed'], 'more effect')} not listed"))


def _text_violation(report: dict[str, Any], v: dict[str, Any], console: Console) -> None:
    """A violation (or an intervention's effect) in two lines: what, where and why; the frame."""
    line = Text()
    line.append(printable(f"{v['rule_id']} "), style=_STYLE[v["severity"]])
    line.append(printable(f"[{v['severity']}] {conn_words(report, v)} {v['dir'] or ''}{side_words(report, v)} "
                          f"+{v['t_rel_s']:.3f}s  "))
    line.append(printable(v["detail"]))
    console.print(line)
    frame = shorten(v["frame"], TEXT_FRAME)
    console.print(Text(printable(f"    {frame}"), style="dim"), _plain(console, f"  ({v['section']})"),
                  overflow="fold")


def _text_violations(report: dict[str, Any], console: Console) -> None:
    console.print(Text("Violations", style="bold"))
    for v in report["violations"]:
        _text_violation(report, v, console)
    if report["violations_not_listed"]:
        console.print(_plain(console, f"… and {report['violations_not_listed']:,} more not listed"))
    console.print(_table("Violations by rule", [("rule", "left"), ("count", "right")],
                         [[rule_id, n] for rule_id, n in report["rule_counts"].items()]))


def _text_latency_and_checksums(report: dict[str, Any], console: Console) -> None:
    for label, rows in latency_tables(report):
        title = f"Latency by request, {label}" if label else "Latency by request"
        columns: list[tuple[str, JustifyMethod]] = [("request", "left"), ("count", "right"), ("p50", "right"),
                                                    ("p95", "right"), ("p99", "right"), ("max", "right")]
        console.print(_table(title, columns,
                             [[r["request"], f"{r['count']:,}", duration(r["p50_ns"]), duration(r["p95_ns"]),
                               duration(r["p99_ns"]), duration(r["max_ns"])] for r in rows]))
    for title, n in report["unanswered"].items():
        console.print(_plain(console, f"Never answered: {n} × {title}", "yellow"))

    for c in report["set_configurations"]:
        ok = "ok" if c["ok"] else f"expected {c['expected']}"
        fits = ", ".join(c["satisfies"]) or "no candidate rule"
        console.print(_plain(console, f"Set Configuration {conn_words(report, c)}: checksum {c['checksum']} ({ok}); "
                                      f"fits: {fits}"))


_MD_INLINE = re.compile(r"([\\`*_\[\]|~])")  # what Markdown (GFM tables too) reads as syntax anywhere
_MD_LINE_START = re.compile(r"^(\s*\d*)([-+#.)])(?=\s|$)")  # ... and what starts a list or heading


def md_text(value: object) -> str:
    """A value as Markdown text that reads as itself: control characters shown
    escaped, Markdown syntax backslash-escaped, and <, > and & as entities, so
    nothing from a recording becomes a link, a table cell or live HTML."""
    text = _MD_LINE_START.sub(r"\1\\\2", _MD_INLINE.sub(r"\\\1", printable(str(value))))
    return text.replace("&", "&amp;").replace("<", "&lt;").replace(">", "&gt;")


def md_code(text: str) -> str:
    """Text (a frame as escaped bytes) as a Markdown code span in a table cell:
    shown exactly, backticks and all (the fence is longer than any run of them
    inside); code spans are never HTML, and a pipe is escaped as GFM tables ask."""
    text = printable(text)
    if not text.strip():
        return text and f"`{text}`"  # an empty span is no span; spaces alone are kept as they are
    fence = "`" * (max((len(run) for run in re.findall("`+", text)), default=0) + 1)
    # one space each side is taken off a span that begins and ends with one: pad
    # a span that would lose a space or whose backticks would touch the fence
    pad = " " if text[0] == "`" or text[-1] == "`" or (text[0] == " " and text[-1] == " ") else ""
    return f"{fence}{pad}{text.replace('|', chr(92) + '|')}{pad}{fence}"


def render_markdown(report: dict[str, Any]) -> str:
    """Every value goes through ``md_text`` or ``md_code``: a report is often
    rendered where HTML in it would run (a CI page, a wiki)."""
    t = md_text
    rule = report["checksum_rule"]
    out = [
        "# whiztap conformance report",
        "",
        f"{t(headline(report))}. Spec Rev {t(report['spec_revision'])}; checksum rule {md_code(rule['name'])} "
        f"({t(rule['description'])}).",
        "",
        f"**{t(verdict(report))}**",
        "",
    ]
    assumed = assumed_words(report)
    if assumed:
        out += [f"{t(assumed)}.", ""]
    for table in report.get("fleet", ()):
        out += _md_fleet(table)
    out += [
        "## Connections",
        "",
        "| file | conn | client | mode | handshake | items | violations |",
        "|---|---:|---|---|---|---:|---:|",
    ]
    for c in report["connections"]:
        out.append(f"| {t(c['file'])} | {c['conn']} | {t(c['client'] or '-')} | {t(c['mode'])} | {t(c['handshake'])} "
                   f"| {c['frames']} | {sum(c['violations'].values())} |")
    if "interventions" in report:
        out += _md_interventions(report)
    out += ["", "## Violations", ""]
    if report["violations"]:
        out += _md_violation_rows(report, report["violations"])
        if report["violations_not_listed"]:
            out.append(f"\n… and {report['violations_not_listed']:,} more not listed.")
    else:
        out.append("None.")
    for label, rows in latency_tables(report):
        out += ["", f"## Latency, {t(label)}" if label else "## Latency", "",
                "| request | count | p50 | p95 | p99 | max |", "|---|---:|---:|---:|---:|---:|"]
        for row in rows:
            out.append(f"| {t(row['request'])} | {row['count']} | {duration(row['p50_ns'])} | "
                       f"{duration(row['p95_ns'])} | {duration(row['p99_ns'])} | {duration(row['max_ns'])} |")
    if report["unanswered"]:
        out += ["", "Never answered: " + ", ".join(f"{n} × {t(title)}" for title, n in report["unanswered"].items())]
    if report["set_configurations"]:
        files = several_files(report)
        out += ["", "## Set Configuration checksums", "", ("| file " if files else "") + "| conn | checksum | expected "
                "| fits |", ("|---" if files else "") + "|---:|---:|---:|---|"]
        for c in report["set_configurations"]:
            out.append((f"| {t(c['file'])} " if files else "") + f"| {c['conn']} | {c['checksum']} | {c['expected']} "
                       f"| {t(', '.join(c['satisfies']) or '-')} |")
    if report.get("unreadable"):
        out += ["", "## Not in this report (could not be read)", ""]
        out += [f"- {t(u['error'])}" for u in report["unreadable"]]
    return "\n".join(out) + "\n"


def _md_fleet(table: dict[str, Any]) -> list[str]:
    title, by_day = fleet_headings(table)
    groups, days = fleet_rows(table)
    out = []
    for heading, columns, rows in ((title, FLEET_COLUMNS, groups), (by_day, FLEET_DAY_COLUMNS, days)):
        head = " | ".join(md_text(c) for c in [fleet_key(table), *columns])
        out += [f"## {md_text(heading)}", "", f"| {head} |",
                "|---|" + "".join("---:|" if c in _NUMERIC else "---|" for c in columns)]
        out += ["| " + " | ".join(md_text(cell) for cell in row) + " |" for row in rows]
        out.append("")
    return out


def _md_violation_rows(report: dict[str, Any], violations: list[dict[str, Any]]) -> list[str]:
    """A table of violations (or effects); with a side column when the proxy stood in the middle."""
    middle = "interventions" in report
    files = several_files(report)
    rows = ["| rule | severity |" + (" file |" if files else "") + " conn |" + (" side |" if middle else "")
            + " t (s) | frame | detail |",
            "|---|---|" + ("---|" if files else "") + "---:|" + ("---|" if middle else "") + "---:|---|---|"]
    for v in violations:
        file = f" {md_text(v['file'])} |" if files else ""
        side = f" {md_text(side_cell(v))} |" if middle else ""
        rows.append(f"| {md_code(v['rule_id'])} | {md_text(v['severity'])} |{file} {v['conn']} |{side} "
                    f"{v['t_rel_s']:.3f} | {md_code(shorten(v['frame'], MD_FRAME))} | {md_text(v['detail'])} |")
    return rows


def _md_interventions(report: dict[str, Any]) -> list[str]:
    heading, rows = intervention_lines(report)
    out = ["", "## Interventions", "", f"{md_text(heading)}."]
    if rows:
        out += ["", "| cause | count | actions |", "|---|---:|---|"]
        out += [f"| {md_code(cause)} | {n} | {md_text(actions)} |" for cause, n, actions in rows]
    section = report["interventions"]
    if section["effects"]:
        out += ["", f"{md_text(EFFECTS_HEADING)}:", ""] + _md_violation_rows(report, section["effects"])
    if section["effects_not_listed"]:
        out.append(f"\n… and {plural(section['effects_not_listed'], 'more effect')} not listed.")
    return out
