"""How a recording is told to the person running it: the wall-clock time of a
violation seen live, the lines printed when a recording ends (``record``
and ``capture`` print the same summary), and the verdict as plain data.

In the middle the verdict is ``whiztap analyze``'s own, live: the writer's
``Recorder`` feeds a ``Judge`` (``whiztap.analyzer.analysis.verdict``) the
events it writes, as the file has them, reports ``verdict_dict`` to the proxy
as it changes (``GET /state`` serves the latest) and closes with it.
"""

from __future__ import annotations

import datetime
from collections.abc import Iterable
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.analysis.verdict import Verdict
from whiztap.analyzer.protocol.text import human_bytes, plural

if TYPE_CHECKING:
    from whiztap.analyzer.mitm.faults import Fault


def clock_text(t_ns: int) -> str:
    """Local time of day with microseconds, as a live line shows when something happened."""
    return datetime.datetime.fromtimestamp(t_ns / 1e9).strftime("%H:%M:%S.%f")


def verdict_dict(verdict: Verdict, open_connections: int, interventions: int) -> dict[str, Any]:
    """A verdict as plain data (``GET /state``'s ``verdict``, the closing
    summary's): whether the traffic so far passes as ``analyze`` decides it
    (``failing``: why not), violations by severity, side and rule, the
    interventions' effects by severity (neither side's), the connections
    seen and those still open (judged as if they ended now), the interventions."""
    return {"passed": verdict.passed, "failing": verdict.failing, "threshold": str(verdict.threshold),
            "violations": dict(verdict.by_severity), "sides": dict(verdict.by_side), "rules": dict(verdict.by_rule),
            "effects": dict(verdict.effects_by_severity), "connections": verdict.connections,
            "open": open_connections, "interventions": interventions}


def summary_lines(summary: dict, what: str) -> list[str]:
    """The lines printed when a recording ends; ``summary``: the writer's (with
    its files' total ``size``), ``what``: 'recorded', 'captured'.  The
    violations are those ``whiztap analyze`` counts in the file: in the
    middle, its verdict (``verdict.py``)."""
    frames, nbytes, violations = summary["frames"], summary["bytes"], summary["violations"]
    files = summary["files"]
    where = files[0] if len(files) == 1 else f"{len(files)} files ({files[0]} ... {files[-1]})" if files else "no file"
    per_dir = "; ".join(f"{d} {plural(frames.get(d, 0), 'frame')} {human_bytes(nbytes.get(d, 0))}"
                        for d in ("c2s", "s2c"))
    counts = ", ".join(plural(violations.get(s, 0), s, "info" if s == "info" else None)
                       for s in ("error", "warning", "info"))
    lines = [f"{what} {plural(summary['connections'], 'connection')} into {where} ({human_bytes(summary['size'])}, "
             f"{plural(summary['messages'], 'message')})",
             f"  {per_dir}",
             f"  violations: {counts}"]
    if summary.get("ring") is not None:  # --ring: incident files only
        lines[0:1] = ring_lines(summary, what)
    verdict = summary.get("verdict")
    if verdict is not None:  # in the middle: the counts are analyze's verdict, each side judged on its own
        effects = sum(verdict["effects"].values())
        lines.append(f"  in the middle: {plural(verdict['interventions'], 'intervention')}"
                     + (f", {plural(effects, 'effect')} of them (no side's violation)" if effects else "")
                     + f"; {'PASS' if verdict['passed'] else 'FAIL'}, as whiztap analyze judges the file")
    if summary.get("quiet_faults"):  # the proxy in the middle's faults that chose no frame (Recording.stop)
        lines.append(f"  faults that chose no frame: {', '.join(summary['quiet_faults'])}")
    return lines


def ring_lines(summary: dict, what: str) -> list[str]:
    """``record --ring``'s first lines: the window kept, how many incidents and
    where, each with the trigger that began it (and how many more it took in)."""
    ring = summary["ring"]
    incidents = ring["incidents"]
    head = f"{what} {plural(summary['connections'], 'connection')} through a {ring['window']} ring: "
    if not incidents:
        return [head + "no incident, so no file written"]
    lines = [head + f"{plural(len(incidents), 'incident')} ({human_bytes(summary['size'])}, "
             f"{plural(summary['messages'], 'message')})"]
    for incident in incidents:
        more = incident["triggers"] - 1
        lines.append(f"  {incident['path']}: {incident['trigger']}"
                     + (f" (and {plural(more, 'trigger')} more while it was written)" if more else ""))
    return lines


def fault_lines(faults: Iterable[Fault]) -> list[str]:
    """The faults a run starts with, in words, one line each, as ``record``,
    ``tui`` and ``demo`` print them at start (``fault-1: delay 200 ms, s2c,
    all frames``): a SPEC that says something else than meant shows before
    any traffic."""
    return [f"{fault.name}: {fault.spec.explain()}" for fault in faults]
