"""The fleet report: a run's violations grouped by metadata keys and by day.

A team records every robot every day and asks one question of thousands of
recordings: which rules break, on which robots and firmware versions, since
when.  Each recording carries metadata (``whiztap record --meta robot=r7
--meta firmware=2.3``, besides the keys every recording has: ``host``,
``source``, ...), so a run's report can be cut by any key, or by several
together (``--group-by robot,firmware``).

The day of a recording is the UTC date its recording began (``start_time_ns``
in its metadata; for a file without one, its first traffic).  Not the
violations' own times: a report holds every violation's count but only the
first 10,000 in full, so days taken from violation times could not add up to
the counts; and a team that records each robot daily has one recording per
robot per day anyway.  A recording that runs past midnight counts on the day
it began.

Everything here is computed from the merged ``Analysis`` (its connections'
per-rule counts and each file's metadata), so a fleet table is as exact as
the merge: the same whether one process or a cluster did the work.
"""

from __future__ import annotations

import datetime
import re
from collections import Counter
from dataclasses import dataclass, field
from typing import Any

from whiztap.analyzer.analysis.facts import NS, Analysis
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.rules import RULES, Severity

DAY_SOURCE = "start_time"  # what a recording's day is taken from (the report says so)
_KEY = re.compile(r"^[A-Za-z_][A-Za-z0-9_.-]{0,63}$")


class GroupByError(WhiztapError, ValueError):
    """A --group-by that names no usable key; one line."""


def parse_group_by(text: str) -> tuple[str, ...]:
    """``robot`` or ``robot,firmware``: the keys one fleet table groups by."""
    keys = tuple(k.strip() for k in text.split(","))
    for key in keys:
        if not _KEY.match(key):
            raise GroupByError(f"--group-by {text!r}: {key!r} is not a metadata key (letters, digits, _ . -)")
    if len(set(keys)) != len(keys):
        raise GroupByError(f"--group-by {text!r} names a key twice")
    return keys


@dataclass
class _Tally:
    """What one group (or one group on one day) adds up to."""

    recordings: int = 0
    connections: int = 0
    frames: int = 0
    rules: Counter = field(default_factory=Counter)

    def add(self, other: _Tally) -> None:
        self.recordings += other.recordings
        self.connections += other.connections
        self.frames += other.frames
        self.rules.update(other.rules)


def recording_day(metadata: dict[str, str], first_ns: int | None) -> str | None:
    """The UTC date (YYYY-MM-DD) a recording began: its metadata's
    ``start_time_ns``, else ``start_time``, else its first traffic; None when
    nothing says."""
    ns = metadata.get("start_time_ns", "")
    if ns.isdigit():
        return _date(int(ns))
    try:
        start = datetime.datetime.fromisoformat(metadata.get("start_time", ""))
    except ValueError:
        return _date(first_ns) if first_ns is not None else None
    if start.tzinfo is None:
        start = start.replace(tzinfo=datetime.UTC)
    return start.astimezone(datetime.UTC).date().isoformat()


def _date(ns: int) -> str:
    return datetime.datetime.fromtimestamp(ns // NS, datetime.UTC).date().isoformat()


def _files(analysis: Analysis, ignore: frozenset[str]) -> dict[str, tuple[str | None, _Tally]]:
    """Each file's day and tally (ignored rules left out)."""
    tallies = {f: _Tally(recordings=1) for f in analysis.files}
    first: dict[str, int] = {}
    for c in analysis.connections:
        tally = tallies.setdefault(c.file, _Tally(recordings=1))
        tally.connections += 1
        tally.frames += sum(c.frames.values())
        tally.rules.update({r: n for r, n in c.violations.items() if n and r not in ignore})
        if c.first_ns is not None:
            first[c.file] = min(first.get(c.file, c.first_ns), c.first_ns)
    return {f: (recording_day(analysis.metadata.get(f, {}), first.get(f)), t) for f, t in tallies.items()}


def fleet_tables(analysis: Analysis, group_by: list[tuple[str, ...]], threshold: Severity = Severity.ERROR,
                 ignore: frozenset[str] = frozenset()) -> list[dict[str, Any]]:
    """One table per key set: its groups, each with its totals, its rules
    (count, first and last day broken) and its days (the JSON report's ``fleet``)."""
    files = _files(analysis, ignore)
    tables = []
    for keys in group_by:
        groups: dict[tuple, dict[str | None, _Tally]] = {}
        for name, (day, tally) in files.items():
            meta = analysis.metadata.get(name, {})
            value = tuple(meta.get(k) for k in keys)
            groups.setdefault(value, {}).setdefault(day, _Tally()).add(tally)
        rows = [_group(keys, value, days, threshold) for value, days in sorted(groups.items(), key=_order)]
        tables.append({"group_by": list(keys), "day_of": DAY_SOURCE, "groups": rows})
    return tables


def _order(item: tuple[tuple, Any]) -> tuple:
    """Groups by value, a recording without the key after those with it."""
    return tuple((v is None, v or "") for v in item[0])


def _group(keys: tuple[str, ...], value: tuple, days: dict[str | None, _Tally],
           threshold: Severity) -> dict[str, Any]:
    total = _Tally()
    since: dict[str, str | None] = {}
    last: dict[str, str | None] = {}
    ordered = sorted(days.items(), key=lambda d: (d[0] is None, d[0] or ""))
    for day, tally in ordered:
        total.add(tally)
        for rule_id in tally.rules:
            since.setdefault(rule_id, day)
            if day is not None:
                last[rule_id] = day
    by_severity = {str(s): 0 for s in (Severity.ERROR, Severity.WARNING, Severity.INFO)}
    for rule_id, n in total.rules.items():
        by_severity[str(RULES[rule_id].severity)] += n
    return {
        "group": dict(zip(keys, value)),
        "recordings": total.recordings, "connections": total.connections, "frames": total.frames,
        "violations": sum(total.rules.values()),
        "violations_by_severity": by_severity,
        "passed": not any(RULES[r].severity >= threshold for r in total.rules),
        "rules": [{"rule_id": r, "severity": str(RULES[r].severity), "count": total.rules[r],
                   "since": since[r], "last": last.get(r)} for r in RULES if total.rules.get(r)],
        "days": [{"day": day, "recordings": t.recordings, "connections": t.connections, "frames": t.frames,
                  "violations": sum(t.rules.values()), "rule_counts": {r: t.rules[r] for r in RULES if t.rules.get(r)}}
                 for day, t in ordered],
    }


def keys_found(analysis: Analysis, keys: tuple[str, ...]) -> bool:
    """Whether any recording of the run carries one of these keys."""
    return any(k in meta for meta in analysis.metadata.values() for k in keys)
