"""``whiztap cat``: every item of a recording, decoded and checked, as lines."""

from __future__ import annotations

import os
from collections.abc import Iterator
from typing import IO, Any

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import checksum_rule_option, force_option, limits_from, limits_options
from whiztap.analyzer.cli.reading import one_recording, scan_recording

TEXT_SHOWN = 200  # characters of an item's escaped bytes on a line of 'cat'; longer ones end in …


@click.command("cat")
@click.argument("inputs", nargs=-1, required=True, metavar="RECORDING")
@click.option("--format", "fmt", type=click.Choice(["text", "jsonl"]), default="text", show_default=True)
@click.option("-o", "--output", type=click.Path(dir_okay=False, allow_dash=True), default=None,
              help="Write to this file ('-': standard output, the default).")
@force_option
@click.option("--filter", "filter_text", default="", metavar="WORDS",
              help="The TUI filter bar's words, e.g. \"kind:response ch:12 violations\" (docs/tui.md).")
@click.option("--conn", "conns", type=int, multiple=True, help="Only this connection; repeatable.")
@click.option("--dir", "direction", type=click.Choice(["c2s", "s2c"]), default=None, help="Only one direction.")
@click.option("--kind", "kinds", multiple=True, metavar="KIND",
              help="Only items of this kind (command, response, config, set_config, handshake, password, "
                   "image, eol, unframed); repeatable.")
@click.option("--channel", "channels", type=int, multiple=True, help="Only frames about this channel; repeatable.")
@click.option("--since", type=float, default=None, help="Seconds from the start of the recording.")
@click.option("--until", type=float, default=None, help="Seconds from the start of the recording (exclusive).")
@click.option("--violations-only", is_flag=True, help="Only items that break a rule.")
@click.option("--interventions", "changes", type=click.Choice(["show", "hide", "only"]), default="show",
              show_default=True,
              help="Lines for the changes the proxy made when it stood in the middle (~ #N): shown among the "
                   "items, hidden, or shown alone.  They follow --conn, --dir, --kind, --since, --until and "
                   "free text (in the cause or the frame); --channel and --violations-only leave them out.")
@click.option("--follow", "-f", is_flag=True,
              help="Tail a recording being written (its .mcap.part, then each later part) until it is finished.")
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@limits_options
def cat_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, filter_text: str,
                conns: tuple[int, ...], direction: str | None, kinds: tuple[str, ...], channels: tuple[int, ...],
                since: float | None, until: float | None, violations_only: bool, changes: str, follow: bool,
                checksum_rule: str, answer_timeout: float, max_frame: int, max_image: int) -> None:
    """Print every item of a recording in time order, decoded and checked.

    RECORDING is a file, a split recording (its first part, its folder or a
    glob), or with --follow a .mcap.part being written.  Streams: the first
    lines appear at once, and memory stays flat however long the recording is.
    """
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.traffic import Data, Intervention

    item_filter = _cat_filter(filter_text, conns, direction, kinds, channels, since, until, violations_only)
    limits = limits_from(answer_timeout, max_frame, max_image)
    if follow:
        if len(inputs) != 1 or not os.path.isfile(inputs[0]):
            fail(f"--follow takes one file being written (NAME.mcap.part), got {' '.join(inputs) or 'none'}")
        records = _followed(inputs[0])
        name = inputs[0]
        # the part it starts from, and the name the recorder renames it to
        read: list[str] = [inputs[0], inputs[0].removesuffix(".part")]
    else:
        recording = one_recording(inputs)
        records, name = scan_recording(recording), str(recording.name)
        read = list(map(str, recording.parts))
    check_output(output, read, force=force)
    analyzer = Analyzer(name, checksum_rule, limits)
    with output_stream(output, force) as out:
        printer = _CatPrinter(fmt, item_filter, out)
        for event in records:
            if type(event) is Intervention:
                if changes != "hide":
                    printer.change(event)
            elif changes != "only":
                printer.show(event.conn, analyzer.receive(event))
            elif type(event) is Data:
                printer.start_at(event.t_ns)  # times count from the first traffic, as when items are shown
        for conn, events in analyzer.close_all() if changes != "only" else ():
            printer.show(conn, events)


def _cat_filter(text: str, conns, direction, kinds, channels, since, until, violations_only):  # noqa: ANN001, ANN202
    """The --filter words, narrowed by the separate options."""
    from dataclasses import replace

    from whiztap.analyzer.protocol.framing import ItemKind
    from whiztap.analyzer.analysis.item_filter import FilterSyntaxError, parse_filter

    try:
        item_filter = parse_filter(text)
    except FilterSyntaxError as e:
        fail(f"--filter: {e}")
    try:
        wanted_kinds = frozenset(ItemKind(k) for k in kinds)
    except ValueError as e:
        fail(f"{e}; kinds are {', '.join(k.value for k in ItemKind)}")
    given = {"conns": frozenset(conns), "direction": direction, "kinds": wanted_kinds,
             "channels": frozenset(channels), "since_s": since, "until_s": until,
             "violations_only": violations_only or None}
    return replace(item_filter, **{k: v for k, v in given.items() if v})


def _followed(path: str) -> Iterator[Any]:
    """The traffic of a recording being written, until it is finished or Ctrl-C."""
    import threading

    from whiztap.analyzer.recording.scan import RecordingError
    from whiztap.analyzer.recording.sets import Stopped, follow

    try:
        yield from follow(path, threading.Event())
    except Stopped:
        return
    except RecordingError as e:
        fail(f"{path}: {e}")
    except OSError as e:
        fail(f"{path}: cannot read ({e.strerror})")


class _CatPrinter:
    def __init__(self, fmt: str, item_filter, out: IO[str]) -> None:  # noqa: ANN001
        from whiztap.analyzer.protocol.describe import fields, meaning
        from whiztap.analyzer.protocol.text import escape, printable, shorten

        self.fmt = fmt
        self.filter = item_filter
        self.start: int | None = None
        self._meaning, self._fields, self._escape, self._shorten = meaning, fields, escape, shorten
        self._printable = printable  # a line says what files and peers said: shown, never obeyed
        self._out = out
        self._colour = out.isatty()
        self._changes = 0  # interventions seen: each line's number

    def show(self, conn: int, events: list) -> None:  # noqa: ANN001
        from whiztap.analyzer.protocol.observations import LateViolation

        for e in events:
            if type(e) is LateViolation:
                if self.filter.accepts(conn, e.about, self._start(e.t_ns), late=True):
                    self._late(conn, e)
                continue
            if self.filter.accepts(conn, e, self._start(e.item.t_end_ns)):
                self._item(conn, e)

    def _start(self, t_ns: int) -> int:
        if self.start is None:
            self.start = t_ns
        return self.start

    def start_at(self, t_ns: int) -> None:
        """Traffic at ``t_ns`` that no line shows: times count from the first."""
        self._start(t_ns)

    def _item(self, conn: int, e) -> None:  # noqa: ANN001
        item = e.item
        rules = [v.rule_id for v in e.violations]
        if self.fmt == "jsonl":
            import json

            from whiztap.analyzer.recording.encode import cat_line

            self._out.write(json.dumps(cat_line(conn, e)) + "\n")
            return
        rel = (item.t_end_ns - (self.start or 0)) / 1e9
        mark = f"  ! {' '.join(rules)}" if rules else ""
        text = self._shorten(self._escape(item.raw), TEXT_SHOWN)  # the JSON lines keep it whole
        line = self._printable(f"{rel:12.6f} c{conn} {e.direction} {item.kind:10} {text}  {self._meaning(e)}{mark}")
        if self._colour and rules:
            line = click.style(line, fg="red" if max(v.severity for v in e.violations) >= 3 else "yellow")
        self._out.write(line + "\n")

    def _late(self, conn: int, e) -> None:  # noqa: ANN001
        v = e.violation
        if self.fmt == "jsonl":
            import json

            self._out.write(json.dumps({
                "t_ns": e.t_ns, "conn": conn, "dir": str(e.about.direction), "kind": "late_violation",
                "raw_b64": None, "fields": {"about_index": e.about.index, "detail": v.detail},
                "violations": [v.rule_id]}) + "\n")
            return
        rel = (e.t_ns - (self.start or 0)) / 1e9
        self._out.write(self._printable(f"{rel:12.6f} c{conn} {v.rule_id}: {v.detail}") + "\n")

    def change(self, e) -> None:  # noqa: ANN001 - an Intervention
        """A change the proxy made, numbered in order: ``~ #N``, the direction,
        the action, the frame (before -> after when it was changed) and why."""
        self._changes += 1
        if not _shows_change(self.filter, e, self._start(e.t_ns)):
            return
        if self.fmt == "jsonl":
            import base64
            import json

            self._out.write(json.dumps({
                "t_ns": e.t_ns, "conn": e.conn, "dir": str(e.direction), "kind": "intervention", "raw_b64": None,
                "fields": {"number": self._changes, "action": e.action.value, "cause": str(e.cause),
                           "source": e.cause.source.value, "index": e.index, "held": e.held, "item_kind": e.kind,
                           "before_b64": base64.b64encode(e.before).decode(),
                           "after_b64": base64.b64encode(e.after).decode(), "detail": e.detail},
                "violations": []}) + "\n")
            return
        rel = (e.t_ns - (self.start or 0)) / 1e9
        cause = f"{e.cause} (held #{e.held})" if e.held else str(e.cause)
        why = f"{cause}; {e.detail}" if e.detail else cause
        line = self._printable(f"{rel:12.6f} c{e.conn} ~ #{self._changes} {e.direction} {e.action}  "
                               f"{self._shorten(_change_text(e, self._escape), TEXT_SHOWN)}  ({why})")
        self._out.write((click.style(line, fg="cyan") if self._colour else line) + "\n")


def _change_text(e, escape) -> str:  # noqa: ANN001
    """The frame an intervention is about: before -> after when it changed, else the one there is."""
    if e.before and e.after and e.before != e.after:
        return f"{escape(e.before)} -> {escape(e.after)}"
    return escape(e.before or e.after)


def _shows_change(item_filter, e, start_ns: int) -> bool:  # noqa: ANN001
    """Whether an intervention's line passes the filter: the words that fit a
    change (connection, direction, the frame's kind, time, text in its cause or
    frame) apply; those only items have (channel, violations) leave it out."""
    from whiztap.analyzer.analysis.item_filter import NS
    from whiztap.analyzer.protocol.text import escape

    f = item_filter
    rel = (e.t_ns - start_ns) / NS
    if f.channels or f.violations_only or (f.conns and e.conn not in f.conns):
        return False
    if (f.direction and str(e.direction) != f.direction) or (f.kinds and e.kind not in f.kinds):
        return False
    if (f.since_s is not None and rel < f.since_s) or (f.until_s is not None and rel >= f.until_s):
        return False
    needle = f.text.lower()
    return not needle or any(needle in text.lower() for text in (str(e.cause), e.action, escape(e.before), escape(e.after)))
