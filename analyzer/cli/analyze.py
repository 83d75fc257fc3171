"""``whiztap analyze``: recordings checked against the spec, as a report.

Recordings are read with ``whiztap.analyzer.recording.scan.RecordingScan`` (a
fast single pass over the file) and sessions are rebuilt from the raw TCP
reads, never from decoded fields stored in the file.
"""

from __future__ import annotations

import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from whiztap.analyzer.analysis.report.formats import FORMATS
from whiztap.analyzer.cli.errors import EXIT_USAGE, CommandFailed, fail, warn
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import (
    assumed_map_options, checksum_rule_option, force_option, limits_assuming, limits_from, limits_options)
from whiztap.analyzer.cli.progress import ByteProgress
from whiztap.analyzer.cli.reading import recordings, scan_recording

if TYPE_CHECKING:
    from whiztap.analyzer.analysis.facts import Analysis
    from whiztap.analyzer.analysis.frame_context import Hits, Views

    FramesOf = Callable[[Analysis], tuple[Views, Hits]]  # the frames around the listed violations
    from whiztap.analyzer.protocol.rules import Severity
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.recording.sets import RecordingSet

_SEVERITIES = ["info", "warning", "error"]
EXIT_NOTHING = 3  # analyze: the recordings hold no traffic to judge
UNWRAPPED = 10_000  # the width text reports are laid out in when not on a terminal


def analyse_file(recording: RecordingSet | Path | str, checksum_rule: str, limits: Limits | None = None,
                 progress: ByteProgress | None = None, label: str | None = None) -> Analysis:
    """One recording (a ``RecordingSet``, a path or a URL's part) analysed in
    this process; ``limits``: an ``whiztap.analyzer.protocol.session.Limits``;
    ``label``: the name the report gives it (default: its first part's), for a
    cluster's worker that reads it by another name.  A recording made with the
    proxy in the middle (its metadata says so) has each side judged by what it
    did (``whiztap.analyzer.analysis.sides``).  Its metadata goes along, for
    the fleet tables."""
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.recording.scan import RecordingError, made_in_the_middle, read_metadata
    from whiztap.analyzer.recording.sets import RecordingSet

    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((recording if not isinstance(recording, str) else Path(recording),))
    label = label or str(recording.name)
    analyzer = Analyzer(label, checksum_rule, limits or Limits(), every_event=False,
                        middle=made_in_the_middle(recording.name))
    receive = analyzer.receive
    for event in scan_recording(recording, progress):
        receive(event)
    analysis = analyzer.finish()
    try:
        analysis.metadata[label] = read_metadata(recording.name)
    except (OSError, RecordingError):  # the scan read the file, so only a file gone since: no keys to group by
        analysis.metadata[label] = {}
    return analysis


def _analyse_or_say_why(recording: RecordingSet, checksum_rule: str, limits: Limits,
                        progress: ByteProgress | None = None, label: str | None = None) -> Analysis | str:
    """``analyse_file``, or the one-line reason it could not be read."""
    try:
        return analyse_file(recording, checksum_rule, limits, progress, label)
    except CommandFailed as e:
        return e.format_message()


def _analyse_in_worker(args: tuple[Any, ...]) -> Analysis | str:
    """Entry point of a worker process, or of a task on a Dask worker:
    errors travel back as text, not tracebacks."""
    from whiztap.analyzer.analysis.throughput import tune_gc

    tune_gc()
    return _analyse_or_say_why(*args)


@click.command("analyze")
@click.argument("inputs", nargs=-1, required=False, metavar="PATH_OR_URL...")
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
              help="Processes for several files [default: one per core when there are many]; "
                   "with --dask local, its workers.")
@click.option("--dask", "dask", default=None, metavar="SCHEDULER",
              help="Run each file as a task on a Dask cluster: its scheduler's address (tcp://HOST:8786), "
                   "or 'local' for a LocalCluster on this machine (docs/fleet.md).")
@click.option("--group-by", "group_by", multiple=True, metavar="KEY[,KEY...]",
              help="Add a fleet table: violations grouped by these metadata keys (robot, firmware, host) "
                   "and by day; repeatable.")
@click.option("-q", "--quiet", is_flag=True, help="No progress bar, no cluster line.")
@click.option("--allow-empty", is_flag=True,
              help="Pass a report on no traffic (no connection, or no server ever reached) instead of exit 3.")
@click.option("--fail-on-interventions", is_flag=True,
              help="With the proxy in the middle: the effects of its interventions (an injected or edited "
                   "frame, and what follows from it) fail the report like violations; by default they are "
                   "listed and fail nothing.")
@limits_options
@assumed_map_options
def analyze_command(inputs: tuple[str, ...], fmt: str, output: str | None, force: bool, list_rules: bool,
                    ignore: tuple[str, ...], severity_threshold: str, checksum_rule: str,
                    jobs: int | None, dask: str | None, group_by: tuple[str, ...], quiet: bool, allow_empty: bool,
                    fail_on_interventions: bool, answer_timeout: float, max_frame: int, max_image: int,
                    channel_map: str | None = None, assume_config: str | None = None) -> None:
    """Check recordings against the spec and report how the sessions behaved.

    PATH_OR_URL: .mcap files, folders, globs, or URLs that fsspec reads
    (file://, s3://, gs://; docs/fleet.md).

    \b
    Exit status:
      0  no violation at or above --severity-threshold (error by default:
         warnings and info do not fail)
      1  a violation at or above the threshold (with --fail-on-interventions,
         also an effect of the proxy's interventions)
      2  an input could not be read (the report covers the others)
      3  nothing to judge: no connection, or the server was never reached
         (--allow-empty passes such a report)
    """
    from whiztap.analyzer.protocol.rules import RULES, Severity
    from whiztap.analyzer.analysis.throughput import tune_gc

    if list_rules:
        for r in RULES.values():
            click.echo(f"{r.id:28} {r.severity!s:8} {r.section}")
        return
    if not inputs:
        fail("no recording given: name one or more .mcap files, folders or URLs (see --help)")
    unknown = [r for r in ignore if r not in RULES]
    if unknown:
        fail(f"unknown rule {unknown[0]!r} in --ignore; 'whiztap analyze --rules' lists them")
    keys = _group_keys(group_by)
    if dask is not None and dask != "local" and jobs is not None:
        fail(f"-j sets the processes of this machine; with --dask {dask} the cluster's workers do the work")
    limits = limits_assuming(limits_from(answer_timeout, max_frame, max_image), channel_map, assume_config)
    found = recordings(inputs, urls=True)
    parts = [p for r in found for p in r.parts]
    check_output(output, parts, force=force)
    tune_gc()
    with ByteProgress(parts, enabled=not quiet) as progress:
        analysis, unreadable = _analyse_all(found, checksum_rule, limits, jobs, progress, dask, quiet)
    _finish(analysis, unreadable, Severity.parse(severity_threshold), frozenset(ignore), keys, fmt, output, force,
            allow_empty, fail_on_interventions, _frames_reader(found, checksum_rule, limits, frozenset(ignore)))


def _frames_reader(found: list[RecordingSet], checksum_rule: str, limits: Limits,
                   ignore: frozenset[str]) -> FramesOf:
    """For the HTML report: the frames around the listed violations and
    effects, read again from the recordings (``frame_context``), once the
    report asks."""
    def read(analysis: Analysis) -> tuple[Views, Hits]:
        from whiztap.analyzer.analysis.frame_context import collect
        from whiztap.analyzer.analysis.report.content import listed_violations

        by_name = {str(r.name): r for r in found}
        # the effects of the proxy's interventions are numbered after the violations (render_html)
        return collect(listed_violations(analysis, ignore) + analysis.effects,
                       lambda file: scan_recording(by_name[file]), checksum_rule, limits)

    return read


def _group_keys(group_by: tuple[str, ...]) -> list[tuple[str, ...]]:
    """Each --group-by as its keys; one line and exit 2 for one that is no key."""
    from whiztap.analyzer.analysis.fleet import GroupByError, parse_group_by

    try:
        return [parse_group_by(text) for text in group_by]
    except GroupByError as e:
        fail(str(e))


def _finish(analysis: Analysis | None, unreadable: list[dict[str, str]], threshold: Severity, ignore: frozenset[str],
            keys: list[tuple[str, ...]], fmt: str, output: str | None, force: bool, allow_empty: bool,
            fail_on_interventions: bool = False, frames: FramesOf | None = None) -> None:
    """The report written, and the exit status it calls for."""
    for u in unreadable:
        warn(u["error"])
    if analysis is None:
        sys.exit(EXIT_USAGE)
    from whiztap.analyzer.analysis.fleet import keys_found
    from whiztap.analyzer.analysis.report.content import build

    for group in keys:
        if not keys_found(analysis, group):
            warn(f"no recording carries the metadata key {' or '.join(group)}: "
                 "its fleet table has one group, (none) ('whiztap info' shows a recording's keys)")
    report = build(analysis, threshold, ignore, unreadable, allow_empty, keys, fail_on_interventions)
    to_stdout = output is None or output == "-"
    report_text = render(report, analysis, fmt, to_stdout and sys.stdout.isatty(),
                         (lambda: frames(analysis)) if frames is not None else None)
    with output_stream(output, force) as out:
        out.write(report_text)
    if report.get("nothing_judged") and not allow_empty:
        warn(f"nothing to judge: {report['nothing_judged']} (--allow-empty to pass anyway)")
        sys.exit(EXIT_USAGE if unreadable else EXIT_NOTHING)
    sys.exit(EXIT_USAGE if unreadable else 0 if report["passed"] else 1)


def _analyse_all(paths: list[RecordingSet], rule_name: str, limits: Limits, jobs: int | None,
                 progress: ByteProgress, dask: str | None = None,
                 quiet: bool = True) -> tuple[Analysis | None, list[dict[str, str]]]:
    """(the merged analysis of the files that could be read, or None if none
    could; {"file", "error"} of those that could not): one bad file among many
    costs only itself.  However the files are shared out (this process, local
    processes, a Dask cluster), results are merged by one ``Merger``, in input
    order, so the report is the same."""
    from whiztap.analyzer.analysis.merge import Merger

    merger = Merger([str(p.name) for p in paths])
    if dask is not None:
        results = _on_cluster(paths, rule_name, limits, jobs, progress, dask, quiet)
    else:
        results = _on_this_machine(paths, rule_name, limits, jobs, progress)
    for index, result in results:
        merger.add(index, result)
    return merger.finish()


def _on_this_machine(paths: list[RecordingSet], rule_name: str, limits: Limits, jobs: int | None,
                     progress: ByteProgress) -> Iterator[tuple[int, Analysis | str]]:
    """(index, result) of each file: here, or in local processes (one per
    core by default when there are four files or more)."""
    workers = jobs if jobs is not None else (min(len(paths), os.cpu_count() or 1) if len(paths) >= 4 else 1)
    if workers <= 1 or len(paths) == 1:
        for index, path in enumerate(paths):
            yield index, _analyse_or_say_why(path, rule_name, limits, progress)
        return
    from concurrent.futures import ProcessPoolExecutor

    with ProcessPoolExecutor(workers) as pool:
        # the bar moves by each file's size as its result comes back
        for index, (path, result) in enumerate(zip(paths, pool.map(_analyse_in_worker,
                                                                   [(p, rule_name, limits) for p in paths]))):
            progress.done_all(path.parts)
            yield index, result


def _on_cluster(paths: list[RecordingSet], rule_name: str, limits: Limits, jobs: int | None,
                progress: ByteProgress, dask: str, quiet: bool) -> Iterator[tuple[int, Analysis | str]]:
    """(index, result) of each file, as a task on a Dask cluster (the
    ``whiztap.runners`` entry point ``dask``: the sniffer's, which talks to the
    scheduler); local paths go as absolute ones (the workers share the files,
    not this process's folder), each labelled as the user named it."""
    from whiztap.analyzer.analysis.merge import Lost, RunnerError

    run = _runner("dask")
    jobs_args = [(_absolute(p), rule_name, limits, None, str(p.name)) for p in paths]
    announce = None if quiet else (lambda line: click.echo(line, err=True))
    try:
        for index, result in run(dask, jobs, _analyse_in_worker, jobs_args, announce):
            progress.done_all(paths[index].parts)
            yield index, f"{paths[index]}: {result.reason}" if isinstance(result, Lost) else result
    except RunnerError as e:
        fail(str(e))


def _runner(name: str) -> Callable[..., Iterator[tuple[int, Any]]]:
    """The ``whiztap.runners`` entry point ``name``, loaded as ``root`` loads
    commands, so that the analyzer imports nothing above it."""
    from importlib.metadata import entry_points

    found = entry_points(group="whiztap.runners", name=name)
    if not found:
        fail(f"--{name} needs whiztap's {name} runner, which is not installed: reinstall whiztap")
    return next(iter(found)).load()


def _absolute(recording: RecordingSet) -> RecordingSet:
    """A recording whose local parts are named from the root."""
    from dataclasses import replace

    return replace(recording, parts=tuple(Path(os.path.abspath(p)) if isinstance(p, Path) else p
                                          for p in recording.parts))


def render(report: dict[str, Any], analysis: Analysis, fmt: str, to_terminal: bool,
           frames: Callable[[], tuple[Views, Hits]] | None = None) -> str:
    """The report in a format, as text ('' when printed straight to the terminal).
    ``frames``: for the HTML report, the frames around its listed violations."""
    if fmt == "json":
        import json

        return json.dumps(report, indent=2) + "\n"
    if fmt == "junit":
        from whiztap.analyzer.analysis.report.junit import render_junit

        return render_junit(report)
    if fmt == "sarif":
        import json

        from whiztap.analyzer.analysis.report.sarif import render_sarif

        return json.dumps(render_sarif(report), indent=2) + "\n"
    if fmt == "github":
        from whiztap.analyzer.analysis.report.github import render_github

        return render_github(report)
    if fmt == "markdown":
        from whiztap.analyzer.analysis.report.text import render_markdown

        return render_markdown(report)
    if fmt == "html":
        from whiztap.analyzer.analysis.report.html import render_html

        views, hits = frames() if frames is not None else ({}, {})
        return render_html(report, analysis, views, hits)
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
