"""``whiztap fuzz server``: spec-aware, stateful fuzzing of a Progwhiz server.

Imports stay light at module level (``whiztap --help`` loads this module); the
fuzzer loads when the command runs.  docs/fuzz.md is the guide.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import say
from whiztap.analyzer.protocol.text import plural
from whiztap.sniffer.cli.params import Address
from whiztap.sniffer.cli.run import run

if TYPE_CHECKING:
    from whiztap.sniffer.fuzz.run import FuzzOptions, FuzzReport


@click.group("fuzz")
def fuzz_command() -> None:
    """Fuzz a Progwhiz implementation with sessions that know the spec (docs/fuzz.md)."""


def _directory(path: str, force: bool) -> Path:
    """The findings folder, made if missing; one line if it cannot be used."""
    directory = Path(path)
    if directory.exists() and not directory.is_dir():
        fail(f"-o {path}: not a folder")
    try:
        directory.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        fail(f"-o {path}: cannot create the folder ({e.strerror or e})")
    old = sorted(p.name for p in (*directory.glob("finding-*.mcap"), *directory.glob("test_finding_*.py")))
    if old and not force:
        fail(f"-o {path}: already holds findings ({old[0]}...); use another folder, or --force to replace them")
    return directory


class _Progress:
    """Executions, findings and elapsed time on stderr, on a terminal only."""

    def __init__(self, enabled: bool) -> None:
        self.bar = None
        if enabled and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import Progress, TextColumn, TimeElapsedColumn

            self.bar = Progress(TextColumn("{task.description}"), TimeElapsedColumn(), transient=True,
                                console=Console(stderr=True))
            self.task = self.bar.add_task("fuzzing")

    def __enter__(self) -> _Progress:
        if self.bar is not None:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar is not None:
            self.bar.stop()

    def __call__(self, report: FuzzReport) -> None:
        if self.bar is not None:
            self.bar.update(self.task, description=f"fuzzing: {plural(report.executions, 'execution')}, "
                                                   f"{plural(len(report.findings), 'finding')}")


async def _fuzz(options: FuzzOptions, command: str | None, directory: Path, progress: _Progress) -> FuzzReport:
    from whiztap.analyzer.fuzz.grammar import Knowledge
    from whiztap.sniffer.fuzz.findings import write
    from whiztap.sniffer.fuzz.run import Found, Fuzzer
    from whiztap.sniffer.fuzz.server import Command, Given, Server

    server: Server = Command(command, options.address) if command else Given()

    async def save(found: Found, knowledge: Knowledge) -> None:
        await write(found, directory, options.address, knowledge, options.password, options.deadline, options.seed)

    return await Fuzzer(options, server, save, progress).run()


def _html(report: FuzzReport) -> str:
    """The HTML page, each finding's minimal session read back from its recording."""
    from whiztap.analyzer.fuzz.report import render_html
    from whiztap.analyzer.analysis.frame_context import read_frames
    from whiztap.analyzer.recording.scan import RecordingError

    sessions = {}
    for found in report.findings:
        try:
            by_conn = read_frames(found.recording)
        except (RecordingError, OSError):
            continue  # the page says the finding has no session to show
        sessions[found.id] = [r for conn in sorted(by_conn) for r in by_conn[conn]]
    return render_html(report.to_json(), sessions)


def _print(report: FuzzReport, fmt: str, quiet: bool, verbose: bool) -> None:
    if fmt == "json":
        click.echo(json.dumps(report.to_json(), indent=2))  # JSON escapes every control character itself
        return
    if fmt == "html":
        click.echo(_html(report), nl=False)
        return
    for found in report.findings:
        v = found.verdict
        shrunk = "" if found.shrunk else ", not shrunk"
        say(f"{found.id}: {v.kind}{f' {v.rule}' if v.rule else ''}, {plural(len(found.session), 'frame')}{shrunk}: "
            f"{found.recording}, {found.test}")
        say(f"  {v.detail}")
        if verbose:
            for frame in found.session:
                say(f"    {frame.shown()}")
    if not quiet:
        say(f"{plural(report.executions, 'execution')} (and {report.shrink_executions} shrinking) in "
            f"{report.seconds:.1f} s against {report.target} ({report.mode}, seed {report.seed}), stopped by "
            f"{report.stopped}: {plural(len(report.findings), 'finding')}")


@fuzz_command.command("server")
@click.argument("address", type=Address("127.0.0.1", "HOST:PORT"), metavar="HOST:PORT")
@click.option("--password", envvar="WHIZTAP_PASSWORD", default=None,
              help="Winsock password (default: $WHIZTAP_PASSWORD, which ps does not show).")
@click.option("--budget", type=click.FloatRange(min=0, min_open=True), required=True, metavar="SECONDS",
              help="How long to fuzz; it only stops the loop (and shrinking), never changes what is sent.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seed of every choice: the same seed against the same server makes the same findings.")
@click.option("--executions", type=click.IntRange(min=1), default=None, metavar="N",
              help="Stop after N executions whatever the time (a run that does not depend on speed).")
@click.option("--deadline", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              metavar="SECONDS", help="How long an owed answer may take before the server is said to hang.")
@click.option("--from", "recordings", multiple=True, metavar="RECORDING",
              help="Seed the corpus with each connection of this whiztap recording; repeatable.")
@click.option("-o", "--output", "out", required=True, metavar="DIR",
              help="Folder for finding-N.mcap and test_finding_N.py (made if missing).")
@click.option("--force", is_flag=True, help="Replace findings already in DIR.")
@click.option("--run", "command", default=None, metavar="CMD",
              help="Start the server with this command line, wait until HOST:PORT accepts, and restart "
                   "it after each crash (without it, a server that stops accepting ends the run).")
@click.option("--format", "fmt", type=click.Choice(["text", "json", "html"]), default="text", show_default=True,
              help="html: the findings on one interactive page, each with its minimal session's frames.")
@click.option("-q", "--quiet", is_flag=True, help="No progress and no summary: only the findings.")
@click.option("-v", "--verbose", is_flag=True, help="Also each finding's frames.")
def server_command(address: tuple[str, int], password: str | None, budget: float, seed: int,
                   executions: int | None, deadline: float, recordings: tuple[str, ...], out: str, force: bool,
                   command: str | None, fmt: str, quiet: bool, verbose: bool) -> None:
    """Fuzz the server at HOST:PORT; exit 1 with findings, 0 without.

    Sessions come from the spec's message and handshake tables (and --from
    recordings), mutated with the grammar in mind; a crash, a hang or a rule
    the server breaks is shrunk to a minimal session and saved in DIR as a
    recording and a pytest."""
    from whiztap.analyzer.errors import WhiztapError
    from whiztap.sniffer.fuzz.findings import recorded_seeds
    from whiztap.sniffer.fuzz.run import FuzzOptions

    directory = _directory(out, force)
    try:
        seeds = recorded_seeds(recordings)
    except WhiztapError as e:
        fail(f"--from {e}")
    options = FuzzOptions(address, (password or "").encode(), seed, budget, executions, deadline, seeds)
    try:
        with _Progress(not quiet) as progress:
            report = run(_fuzz(options, command, directory, progress))
    except WhiztapError as e:
        fail(str(e))
    _print(report, fmt, quiet, verbose)
    sys.exit(1 if report.findings else 0)
