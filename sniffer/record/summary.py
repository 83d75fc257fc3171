"""How a recording is told to the person running it: the wall-clock time of a
violation seen live, and the lines printed when a recording ends (``record``
and ``capture`` print the same summary)."""

from __future__ import annotations

import datetime

from whiztap.analyzer.protocol.text import human_bytes


def clock_text(t_ns: int) -> str:
    """Local time of day with microseconds, as a live line shows when something happened."""
    return datetime.datetime.fromtimestamp(t_ns / 1e9).strftime("%H:%M:%S.%f")


def summary_lines(summary: dict, what: str) -> list[str]:
    """The lines printed when a recording ends; ``summary``: the writer's (with
    its files' total ``size``), ``what``: 'recorded', 'captured'."""
    frames, nbytes, violations = summary["frames"], summary["bytes"], summary["violations"]
    files = summary["files"]
    where = files[0] if len(files) == 1 else f"{len(files)} files ({files[0]} ... {files[-1]})" if files else "no file"
    per_dir = "; ".join(f"{d} {frames.get(d, 0)} frames {human_bytes(nbytes.get(d, 0))}" for d in ("c2s", "s2c"))
    counts = ", ".join(f"{violations.get(s, 0)} {s}" for s in ("error", "warning", "info"))
    return [f"{what} {summary['connections']} connection(s) into {where} ({human_bytes(summary['size'])}, "
            f"{summary['messages']} messages)",
            f"  {per_dir}",
            f"  violations: {counts}"]
