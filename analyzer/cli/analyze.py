"""``whiztap analyze``, ``cat`` and ``info``: what a recording says.

All three read recordings with ``whiztap.analyzer.recording.scan.RecordingScan`` (a fast
single pass over the file) and rebuild sessions from the raw TCP reads, never
from decoded fields stored in the file.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import click

from whiztap.analyzer.cli.root import (
    EXIT_USAGE,
    check_output,
    fail,
    force_option,
    limits_from,
    limits_options,
    output_stream,
    warn,
)
from whiztap.analyzer.analysis.report.formats import FORMATS

_SEVERITIES = ["info", "warning", "error"]
EXIT_NOTHING = 3  # analyze: the recordings hold no traffic to judge
UNWRAPPED = 10_000  # the width text reports are laid out in when not on a terminal
TEXT_SHOWN = 200  # characters of an item's escaped bytes on a line of 'cat'; longer ones end in …


# -- reading ----------------------------------------------------------------------------


def recordings(inputs: tuple[str, ...]):  # noqa: ANN201 - list[RecordingSet], imported lazily
    """What the user named, as recordings (a split one's parts together);
    a line on stderr for each whose parts are not all there."""
    from whiztap.analyzer.recording.sets import RecordingInputError, find_recordings

    try:
        found = find_recordings(inputs)
    except RecordingInputError as e:
        fail(str(e))
    for recording in found:
        if recording.warning():
            warn(recording.warning())
    return found


def scan_recording(recording, progress: ByteProgress | None = None) -> Iterator[Any]:  # noqa: ANN001
    """The traffic events of a recording (a ``RecordingSet``, or one path) in
    recorded order, across its parts.

    Raises ``click`` errors with one-line messages for files that are not
    readable recordings, or end before their footer.
    """
    from whiztap.analyzer.recording.sets import PartError, RecordingSet, scan_set

    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    opener = progress.open if progress is not None else (lambda p: open(p, "rb"))  # noqa: SIM115
    try:
        yield from scan_set(recording, opener)
    except PartError as e:
        from whiztap.analyzer.recording.sets import being_written

        if being_written(e.path):
            fail(f"{e.path} is being written by a running recorder: 'whiztap cat --follow {e.path}' shows it "
                 "as it grows; analyze it once the recorder has finished")
        if e.truncated or e.path.name.endswith(".part"):
            fail(f"{e}; it looks like a recording that was cut short. "
                 f"Run 'whiztap recover {e.path}' to turn it into a complete file")
        fail(str(e))


class ByteProgress:
    """A progress bar over files' bytes, on a terminal, for files that take a
    moment: ``open`` counts what is read through it, ``update`` takes a
    position from a reader that does its own reading (pcap import)."""

    THRESHOLD = 16 * 1024 * 1024

    def __init__(self, paths: list[Path], enabled: bool, doing: str = "analysing") -> None:
        total = sum(p.stat().st_size for p in paths)
        self.bar = None
        if enabled and total >= self.THRESHOLD and sys.stderr.isatty():
            from rich.progress import BarColumn, DownloadColumn, Progress, TimeRemainingColumn

            self.bar = Progress("[progress.description]{task.description}", BarColumn(), DownloadColumn(),
                                TimeRemainingColumn(), transient=True, console=_stderr_console())
            self.task = self.bar.add_task(doing, total=total)

    def __enter__(self) -> ByteProgress:
        if self.bar:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar:
            self.bar.stop()

    def done(self, path: Path) -> None:
        """A whole file was read elsewhere (a worker process)."""
        if self.bar is not None:
            self.bar.advance(self.task, path.stat().st_size)

    def update(self, position: int) -> None:
        """Bytes done so far, in all: for readers that do their own reading."""
        if self.bar is not None:
            self.bar.update(self.task, completed=position)

    def open(self, path: Path) -> IO[bytes]:
        f = open(path, "rb")  # noqa: SIM115 - closed by the caller
        if self.bar is None:
            return f
        bar, task = self.bar, self.task

        class Counting:
            def read(self, n: int = -1) -> bytes:
                data = f.read(n)
                bar.advance(task, len(data))
                return data

            def close(self) -> None:
                f.close()

        return Counting()  # type: ignore[return-value]


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)


def analyse_file(recording, checksum_rule: str, limits=None, progress: ByteProgress | None = None):  # noqa: ANN001
    """One recording (a ``RecordingSet`` or a path) analysed in this process;
    ``limits``: an ``whiztap.analyzer.protocol.session.Limits``."""
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.recording.sets import RecordingSet
    from whiztap.analyzer.protocol.session import Limits

    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    analyzer = Analyzer(str(recording.name), checksum_rule, limits or Limits(), every_event=False)
    receive = analyzer.receive
    for event in scan_recording(recording, progress):
        receive(event)
    return analyzer.finish()


def _analyse_or_say_why(recording, checksum_rule: str, limits, progress: ByteProgress | None = None):  # noqa: ANN001
    """``analyse_file``, or the one-line reason it could not be read."""
    try:
        return analyse_file(recording, checksum_rule, limits, progress)
    except click.ClickException as e:
        return e.format_message()


def _analyse_in_worker(args: tuple):
    """Entry point of a worker process: errors travel back as text, not tracebacks."""
    from whiztap.analyzer.analysis.throughput import tune_gc

    tune_gc()
    return _analyse_or_say_why(*args)


# -- analyze ---------------------------------------------------------------------------


@click.command("analyze")
@click.argument("inputs", nargs=-1, required=False, metavar="FILE_OR_FOLDER...")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="text",
              show_default=True, help="Report format; text is coloured on a terminal.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, allow_dash=True), default=None,
              help="Write the report to this file ('-': standard output, the default).")
@force_option
@click.option("--rules", "list_rules", is_flag=True, help="List every rule (id, severity, spec section) and exit.")
@click.option("--ignore", multiple=True, metavar="RULE", help="Leave this rule out of the report; repeatable.")
@click.option("--severity-threshold", type=click.Choice(_SEVERITIES), default="error", show_default=True,
              help="Exit 1 when a violation at or above this severity remains.")
@click.option("--checksum-rule", default=None, help="Set Configuration checksum rule (see docs/protocol.md).")
@click.option("-j", "--jobs", type=click.IntRange(1, 64), default=None,
              help="Processes for several files [default: one per core when there are many].")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
@click.option("--allow-empty", is_flag=True,
              help="Pass a report on no traffic (no connection, or no server ever reached) instead of exit 3.")
@limits_options
def analyze_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, list_rules: bool,
                    ignore: tuple[str, ...], severity_threshold: str, checksum_rule: str | None,
                    jobs: int | None, quiet: bool, allow_empty: bool, answer_timeout: float, max_frame: int,
                    max_image: int) -> None:
    """Check recordings against the spec and report how the sessions behaved.

    \b
    Exit status:
      0  no violation at or above --severity-threshold (error by default:
         warnings and info do not fail)
      1  a violation at or above the threshold
      2  an input could not be read (the report covers the others)
      3  nothing to judge: no connection, or the server was never reached
         (--allow-empty passes such a report)
    """
    from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
    from whiztap.analyzer.protocol.rules import RULES, Severity
    from whiztap.analyzer.analysis.throughput import tune_gc

    if list_rules:
        for r in RULES.values():
            click.echo(f"{r.id:28} {str(r.severity):8} {r.section}")
        return
    if not inputs:
        fail("no recording given: name one or more .mcap files or folders (see --help)")
    unknown = [r for r in ignore if r not in RULES]
    if unknown:
        fail(f"unknown rule {unknown[0]!r} in --ignore; 'whiztap analyze --rules' lists them")
    rule_name = checksum_rule or DEFAULT_CHECKSUM_RULE
    try:
        get_rule(rule_name)
    except ValueError as e:
        fail(str(e))
    limits = limits_from(answer_timeout, max_frame, max_image)
    found = recordings(inputs)
    check_output(output, [p for r in found for p in r.parts], force=force)
    tune_gc()
    with ByteProgress([p for r in found for p in r.parts], enabled=not quiet) as progress:
        analysis, unreadable = _analyse_all(found, rule_name, limits, jobs, progress)
    for u in unreadable:
        warn(u["error"])
    if analysis is None:
        sys.exit(EXIT_USAGE)
    from whiztap.analyzer.analysis.report.content import build

    report = build(analysis, Severity.parse(severity_threshold), frozenset(ignore), unreadable, allow_empty)
    to_stdout = output is None or output == "-"
    report_text = render(report, analysis, fmt, to_terminal=to_stdout and sys.stdout.isatty())
    with output_stream(output, force) as out:
        out.write(report_text)
    if report.get("nothing_judged") and not allow_empty:
        warn(f"nothing to judge: {report['nothing_judged']} (--allow-empty to pass anyway)")
        sys.exit(EXIT_USAGE if unreadable else EXIT_NOTHING)
    sys.exit(EXIT_USAGE if unreadable else 0 if report["passed"] else 1)


def _analyse_all(paths: list, rule_name: str, limits, jobs: int | None, progress: ByteProgress):  # noqa: ANN001
    """(the merged analysis of the files that could be read, or None if none
    could; {"file", "error"} of those that could not): one bad file among many
    costs only itself."""
    workers = jobs if jobs is not None else (min(len(paths), os.cpu_count() or 1) if len(paths) >= 4 else 1)
    if workers <= 1 or len(paths) == 1:
        results = [_analyse_or_say_why(p, rule_name, limits, progress) for p in paths]
    else:
        from concurrent.futures import ProcessPoolExecutor

        results = []
        with ProcessPoolExecutor(workers) as pool:
            # in order, so the report does not depend on which worker finished first;
            # the bar moves by each file's size as its result comes back
            for path, result in zip(paths, pool.map(_analyse_in_worker, [(p, rule_name, limits) for p in paths])):
                results.append(result)
                for part in path.parts:
                    progress.done(part)
    unreadable = [{"file": str(p.name), "error": r} for p, r in zip(paths, results) if isinstance(r, str)]
    analyses = [r for r in results if not isinstance(r, str)]
    if not analyses:
        return None, unreadable
    merged = analyses[0]
    for other in analyses[1:]:
        merged.merge(other)
    return merged, unreadable


def render(report: dict[str, Any], analysis, fmt: str, to_terminal: bool) -> str:
    """The report in a format, as text ('' when printed straight to the terminal)."""
    if fmt == "json":
        import json

        return json.dumps(report, indent=2) + "\n"
    if fmt == "junit":
        from whiztap.analyzer.analysis.report.junit import render_junit

        return render_junit(report)
    if fmt == "markdown":
        from whiztap.analyzer.analysis.report.text import render_markdown

        return render_markdown(report)
    if fmt == "html":
        from whiztap.analyzer.analysis.report.html import MissingPlotLibrary, render_html

        try:
            return render_html(report, analysis)
        except MissingPlotLibrary as e:
            fail(str(e))
    from rich.console import Console

    from whiztap.analyzer.analysis.report.text import render_text

    if to_terminal:
        render_text(report, Console())
        return ""
    import io

    # to a pipe or a file: never wrapped (a frame split over lines is a frame lost to grep)
    console = Console(record=True, width=UNWRAPPED, force_terminal=False, soft_wrap=True, file=io.StringIO())
    render_text(report, console)
    return console.export_text()


# -- cat --------------------------------------------------------------------------------


def one_recording(inputs: tuple[str, ...]):  # noqa: ANN201 - a RecordingSet, imported lazily
    """The one recording a command reads: a file, a split one's first part, its
    folder or a glob (expanded by the shell or not)."""
    from whiztap.analyzer.recording.sets import RecordingInputError, find_one

    try:
        found = find_one(inputs)
    except RecordingInputError as e:
        fail(f"{e} (see '{click.get_current_context().command_path} --help')")
    if found.warning():
        warn(found.warning())
    return found


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
@click.option("--follow", "-f", is_flag=True,
              help="Tail a recording being written (its .mcap.part, then each later part) until it is finished.")
@click.option("--checksum-rule", default=None, help="Set Configuration checksum rule.")
@limits_options
def cat_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, filter_text: str,
                conns: tuple[int, ...], direction: str | None, kinds: tuple[str, ...], channels: tuple[int, ...],
                since: float | None, until: float | None, violations_only: bool, follow: bool,
                checksum_rule: str | None, answer_timeout: float, max_frame: int, max_image: int) -> None:
    """Print every item of a recording in time order, decoded and checked.

    RECORDING is a file, a split recording (its first part, its folder or a
    glob), or with --follow a .mcap.part being written.  Streams: the first
    lines appear at once, and memory stays flat however long the recording is.
    """
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE

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
    try:
        analyzer = Analyzer(name, checksum_rule or DEFAULT_CHECKSUM_RULE, limits)
    except ValueError as e:
        fail(str(e))
    with output_stream(output, force) as out:
        printer = _CatPrinter(fmt, item_filter, out)
        for event in records:
            printer.show(event.conn, analyzer.receive(event))
        for conn, events in analyzer.close_all():
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


# -- info -------------------------------------------------------------------------------


@click.command("info")
@click.argument("inputs", nargs=-1, required=True, metavar="RECORDING")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True)
def info_command(inputs: tuple[str, ...], fmt: str) -> None:
    """File-level facts: format version, session metadata, time span,
    connections, messages per topic, size, and whether the file is complete.
    A split recording (its first part, folder or a glob) is shown as one, with
    its parts listed."""
    from whiztap.analyzer.recording.info import set_info
    from whiztap.analyzer.protocol.text import printable

    recording = one_recording(inputs)
    path_ = recording.parts[-1]
    try:
        info = set_info(list(recording.parts))
    except OSError as e:
        fail(f"{path_}: cannot read ({e.strerror})")
    except ValueError as e:
        fail(f"{path_}: {e}")
    if fmt == "json":
        import json

        click.echo(json.dumps(info, indent=2))
        return
    # names and metadata come from the file: a terminal must show them, never obey them
    click.echo(f"file            {printable(info['path'])}")
    for part in info.get("parts", []):
        click.echo(f"  part          {printable(part['path'])} ({part['size_bytes']:,} bytes, "
                   f"{printable(part['state'])})")
    click.echo(f"size            {info['size_bytes']:,} bytes")
    click.echo(f"complete        {'yes (indexed)' if info['complete'] else 'NO: ' + printable(info['state'])}")
    version = info["format_version"]
    click.echo(f"format version  {printable(version) if version else 'unknown (not written by whiztap?)'}")
    for key, value in info["metadata"].items():
        click.echo(f"  {printable(key):14} {printable(value)}")
    click.echo(f"time span       {info['start']} .. {info['end']} ({info['duration_s']:.3f} s)")
    click.echo(f"connections     {info['connections']}")
    click.echo("messages per topic")
    for topic, n in info["topics"].items():
        click.echo(f"  {topic:14} {n:,}")
    if not info["complete"] and not info["state"].startswith("being written"):
        click.echo(f"Run 'whiztap recover {printable(str(path_))}' to make a complete, indexed copy.")
