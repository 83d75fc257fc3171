"""``whiztap cat``: every item of a recording, decoded and checked, as lines."""

from __future__ import annotations

import os
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from typing import IO, TYPE_CHECKING, Any

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import (
    assumed_map_options, checksum_rule_option, force_option, limits_assuming, limits_from, limits_options)
from whiztap.analyzer.cli.reading import one_recording, scan_recording

if TYPE_CHECKING:
    from pathlib import Path

    from whiztap.analyzer.analysis.answer_latency import AnswerLatencies
    from whiztap.analyzer.analysis.item_filter import ItemFilter
    from whiztap.analyzer.protocol.observations import Event, LateViolation, Observation
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.recording.remote import RemotePart
    from whiztap.analyzer.traffic import Intervention, TrafficEvent

    # an answer's line, made once its latencies are known: (server ns, client ns) -> line
    LineMaker = Callable[[int | None, int | None], str]

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
@assumed_map_options
def cat_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, filter_text: str,
                conns: tuple[int, ...], direction: str | None, kinds: tuple[str, ...], channels: tuple[int, ...],
                since: float | None, until: float | None, violations_only: bool, changes: str, follow: bool,
                checksum_rule: str, answer_timeout: float, max_frame: int, max_image: int,
                channel_map: str | None = None, assume_config: str | None = None) -> None:
    """Print every item of a recording in time order, decoded and checked.

    RECORDING is a file, a split recording (its first part, its folder or a
    glob), or with --follow a .mcap.part being written.  Streams: the first
    lines appear at once, and memory stays flat however long the recording is.
    """
    item_filter = _cat_filter(filter_text, conns, direction, kinds, channels, since, until, violations_only)
    limits = limits_assuming(limits_from(answer_timeout, max_frame, max_image), channel_map, assume_config)
    first: str | Path | RemotePart
    if follow:
        if len(inputs) != 1 or not os.path.isfile(inputs[0]):
            fail(f"--follow takes one file being written (NAME.mcap.part), got {' '.join(inputs) or 'none'}")
        records = _followed(inputs[0])
        name = first = inputs[0]
        # the part it starts from, and the name the recorder renames it to
        read: list[str] = [inputs[0], inputs[0].removesuffix(".part")]
    else:
        recording = one_recording(inputs)
        records, name, first = scan_recording(recording), str(recording.name), recording.name
        read = list(map(str, recording.parts))
    check_output(output, read, force=force)
    with output_stream(output, force) as out:
        printer = _CatPrinter(fmt, item_filter, out, _answer_latencies(first, checksum_rule, limits),
                              2 * limits.answer_timeout_ns + 1_000_000_000)
        _print(records, printer, name, checksum_rule, limits, changes)


def _answer_latencies(first: str | Path | RemotePart, checksum_rule: str, limits: Limits) -> AnswerLatencies | None:
    """For a recording made in the middle, each answer's latency for the server and for the client."""
    from functools import partial

    from whiztap.analyzer.analysis.answer_latency import AnswerLatencies
    from whiztap.analyzer.recording.scan import made_in_the_middle

    if not made_in_the_middle(first):
        return None
    return AnswerLatencies(partial(limits.session, checksum_rule))


def _print(records: Iterable[TrafficEvent], printer: _CatPrinter, name: str, checksum_rule: str, limits: Limits,
           changes: str) -> None:
    """Every event through the one session (and the two views, in the middle), as lines."""
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.traffic import Data, Intervention

    analyzer = Analyzer(name, checksum_rule, limits)
    both = printer.latencies
    for event in records:
        if both is not None:
            both.receive(event)
        if type(event) is Intervention:
            if changes != "hide":
                printer.change(event)
        elif changes != "only":
            printer.show(event.conn, analyzer.receive(event))
        elif type(event) is Data:
            printer.start_at(event.t_ns)  # times count from the first traffic, as when items are shown
        printer.release(event.t_ns)
    for conn, events in analyzer.close_all() if changes != "only" else ():
        printer.show(conn, events)
    if both is not None:
        both.finish()
    printer.release(None)


def _cat_filter(text: str, conns: tuple[int, ...], direction: str | None, kinds: tuple[str, ...],
                channels: tuple[int, ...], since: float | None, until: float | None,
                violations_only: bool) -> ItemFilter:
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
    given: dict[str, Any] = {"conns": frozenset(conns), "direction": direction, "kinds": wanted_kinds,
             "channels": frozenset(channels), "since_s": since, "until_s": until,
             "violations_only": violations_only or None}
    return replace(item_filter, **{k: v for k, v in given.items() if v})


def _followed(path: str) -> Iterator[TrafficEvent]:
    """The traffic of a recording being written, until it is finished or Ctrl-C."""
    import threading

    from whiztap.analyzer.recording.sets import Follower, PartError, Stopped

    try:
        yield from Follower(path, threading.Event())
    except Stopped:
        return
    except PartError as e:  # its message names the part it is about
        fail(str(e))


class _CatPrinter:
    """Lines in time order.  In the middle (``latencies``), an answer's line
    also says both latencies; the client's may be known only once the answer
    reached the client, so lines wait here (in order) until it is, or until
    the client's view gave up on the request (at most ``HELD`` lines, and
    ``wait_ns`` of recording time)."""

    HELD = 10_000

    def __init__(self, fmt: str, item_filter: ItemFilter, out: IO[str], latencies: AnswerLatencies | None = None,
                 wait_ns: int = 11_000_000_000) -> None:
        from whiztap.analyzer.protocol.describe import fields, meaning
        from whiztap.analyzer.protocol.text import escape, printable, shorten

        self.fmt = fmt
        self.filter = item_filter
        self.start: int | None = None
        self.latencies = latencies
        self.wait_ns = wait_ns  # recording time an answer's line waits for the client's latency, at most
        self._meaning, self._fields, self._escape, self._shorten = meaning, fields, escape, shorten
        self._printable = printable  # a line says what files and peers said: shown, never obeyed
        self._out = out
        self._colour = out.isatty()
        self._changes = 0  # interventions seen: each line's number
        # [line or its maker, conn, request, server ns, t_ns]
        self._held: deque[tuple[str | LineMaker, int, Observation | None, int | None, int]] = deque()

    def show(self, conn: int, events: list[Event]) -> None:
        from whiztap.analyzer.protocol.observations import LateViolation

        for e in events:
            if isinstance(e, LateViolation):
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

    def _write(self, line: str, conn: int = 0, request: Observation | None = None, server: int | None = None,
               t_ns: int = 0, make: LineMaker | None = None) -> None:
        """A line, or (``make``) the maker of an answer's line once the client's latency is known."""
        if make is None and not self._held:
            self._out.write(line + "\n")
        else:
            self._held.append((make or line, conn, request, server, t_ns))

    def release(self, now_ns: int | None) -> None:
        """Write the lines no longer waiting (``now_ns`` None: the end, all of them)."""
        held, limit = self._held, self.wait_ns
        while held:
            line, conn, request, server, t_ns = held[0]
            if not isinstance(line, str):
                known = (self.latencies.client_ns(conn, request)
                         if self.latencies is not None and request is not None else None)
                if known is None and now_ns is not None and len(held) <= self.HELD and now_ns - t_ns <= limit:
                    return
                line = line(server, known.ns if known is not None else None)
            self._out.write(line + "\n")
            held.popleft()

    def _item(self, conn: int, e: Observation) -> None:
        item = e.item
        rules = [v.rule_id for v in e.violations]
        latencies = self.latencies if e.answers is not None else None
        both = latencies is not None
        server = latencies.server_ns(conn, e) if latencies is not None else None
        if self.fmt == "jsonl":
            import json

            from whiztap.analyzer.recording.encode import cat_line

            fields = cat_line(conn, e)
            if not both:
                self._write(json.dumps(fields))
                return
            self._write("", conn, e.answers, server, item.t_end_ns, lambda s, c: json.dumps(
                {**fields, "server_latency_ns": s, "client_latency_ns": c}))
            return
        rel = (item.t_end_ns - (self.start or 0)) / 1e9
        mark = f"  ! {' '.join(rules)}" if rules else ""
        text = self._shorten(self._escape(item.raw), TEXT_SHOWN)  # the JSON lines keep it whole
        line = self._printable(f"{rel:12.6f} c{conn} {e.direction} {item.kind:10} {text}  {self._meaning(e)}{mark}")
        colour = "red" if rules and max(v.severity for v in e.violations) >= 3 else "yellow" if rules else None

        def coloured(line: str) -> str:
            return click.style(line, fg=colour) if self._colour and colour else line

        if not both:
            self._write(coloured(line))
            return
        self._write("", conn, e.answers, server, item.t_end_ns,
                    lambda s, c: coloured(f"{line}  [latency: {_latency_words(s, c)}]"))

    def _late(self, conn: int, e: LateViolation) -> None:
        v = e.violation
        if self.fmt == "jsonl":
            import json

            self._write(json.dumps({
                "t_ns": e.t_ns, "conn": conn, "dir": str(e.about.direction), "kind": "late_violation",
                "raw_b64": None, "fields": {"about_index": e.about.index, "detail": v.detail},
                "violations": [v.rule_id]}))
            return
        rel = (e.t_ns - (self.start or 0)) / 1e9
        self._write(self._printable(f"{rel:12.6f} c{conn} {v.rule_id}: {v.detail}"))

    def change(self, e: Intervention) -> None:
        """A change the proxy made, numbered in order: ``~ #N``, the direction,
        the action, the frame (before -> after when it was changed) and why."""
        self._changes += 1
        if not _shows_change(self.filter, e, self._start(e.t_ns)):
            return
        if self.fmt == "jsonl":
            import base64
            import json

            self._write(json.dumps({
                "t_ns": e.t_ns, "conn": e.conn, "dir": str(e.direction), "kind": "intervention", "raw_b64": None,
                "fields": {"number": self._changes, "action": e.action.value, "cause": str(e.cause),
                           "source": e.cause.source.value, "index": e.index, "held": e.held, "item_kind": e.kind,
                           "before_b64": base64.b64encode(e.before).decode(),
                           "after_b64": base64.b64encode(e.after).decode(), "detail": e.detail},
                "violations": []}))
            return
        rel = (e.t_ns - (self.start or 0)) / 1e9
        cause = f"{e.cause} (held #{e.held})" if e.held else str(e.cause)
        why = f"{cause}; {e.detail}" if e.detail else cause
        line = self._printable(f"{rel:12.6f} c{e.conn} ~ #{self._changes} {e.direction} {e.action}  "
                               f"{self._shorten(_change_text(e, self._escape), TEXT_SHOWN)}  ({why})")
        self._write(click.style(line, fg="cyan") if self._colour else line)


def _latency_words(server: int | None, client: int | None) -> str:
    """``server 0.350 ms, client 300.412 ms``; ``none`` where there is none."""
    def ms(ns: int | None) -> str:
        return "none" if ns is None else f"{ns / 1e6:.3f} ms"

    return f"server {ms(server)}, client {ms(client)}"


def _change_text(e: Intervention, escape: Callable[[bytes], str]) -> str:
    """The frame an intervention is about: before -> after when it changed, else the one there is."""
    if e.before and e.after and e.before != e.after:
        return f"{escape(e.before)} -> {escape(e.after)}"
    return escape(e.before or e.after)


def _shows_change(item_filter: ItemFilter, e: Intervention, start_ns: int) -> bool:
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
    texts = (str(e.cause), e.action, escape(e.before), escape(e.after))
    return not needle or any(needle in text.lower() for text in texts)
