"""``whiztap analyze``: recordings checked against the spec, as a report.

Recordings are read with ``whiztap.analyzer.recording.scan.RecordingScan`` (a
fast single pass over the file) and sessions are rebuilt from the raw TCP
reads, never from decoded fields stored in the file.
"""

from __future__ import annotations

import os
import sys
from pathlib import Path
from typing import Any

import click

from whiztap.analyzer.analysis.report.formats import FORMATS
from whiztap.analyzer.cli.errors import EXIT_USAGE, WhiztapError, fail, warn
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import checksum_rule_option, force_option, limits_from, limits_options
from whiztap.analyzer.cli.progress import ByteProgress
from whiztap.analyzer.cli.reading import recordings, scan_recording

_SEVERITIES = ["info", "warning", "error"]
EXIT_NOTHING = 3  # analyze: the recordings hold no traffic to judge
UNWRAPPED = 10_000  # the width text reports are laid out in when not on a terminal


def analyse_file(recording, checksum_rule: str, limits=None, progress: ByteProgress | None = None):  # noqa: ANN001
    """One recording (a ``RecordingSet`` or a path) analysed in this process;
    ``limits``: an ``whiztap.analyzer.protocol.session.Limits``.  A recording
    made with the proxy in the middle (its metadata says so) has each side
    judged by what it did (``whiztap.analyzer.analysis.sides``)."""
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.recording.scan import made_in_the_middle
    from whiztap.analyzer.recording.sets import RecordingSet
    from whiztap.analyzer.protocol.session import Limits

    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    analyzer = Analyzer(str(recording.name), checksum_rule, limits or Limits(), every_event=False,
                        middle=made_in_the_middle(str(recording.name)))
    receive = analyzer.receive
    for event in scan_recording(recording, progress):
        receive(event)
    return analyzer.finish()


def _analyse_or_say_why(recording, checksum_rule: str, limits, progress: ByteProgress | None = None):  # noqa: ANN001
    """``analyse_file``, or the one-line reason it could not be read."""
    try:
        return analyse_file(recording, checksum_rule, limits, progress)
    except WhiztapError as e:
        return e.format_message()


def _analyse_in_worker(args: tuple):
    """Entry point of a worker process: errors travel back as text, not tracebacks."""
    from whiztap.analyzer.analysis.throughput import tune_gc

    tune_gc()
    return _analyse_or_say_why(*args)


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
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@click.option("-j", "--jobs", type=click.IntRange(1, 64), default=None,
              help="Processes for several files [default: one per core when there are many].")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar.")
@click.option("--allow-empty", is_flag=True,
              help="Pass a report on no traffic (no connection, or no server ever reached) instead of exit 3.")
@limits_options
def analyze_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, list_rules: bool,
                    ignore: tuple[str, ...], severity_threshold: str, checksum_rule: str,
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
    rule_name = checksum_rule
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
