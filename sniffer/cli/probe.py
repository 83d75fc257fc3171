"""``whiztap probe``: a server (or a client) tested actively against the spec (docs/probe.md).

``probe server`` plays the client: the catalogue of ``whiztap.analyzer.probe``
against a live server, one connection per case, each judged by the analyzer's
rules.  Exit status 0 when every case passed (or was skipped), 1 when one
failed, 2 when the probe could not run.  Imports stay light at module level
(``whiztap --help`` loads this module).
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import force_option
from whiztap.analyzer.probe.report import FORMATS
from whiztap.sniffer.cli.params import Address
from whiztap.sniffer.cli.probe_client import probe_client_command
from whiztap.sniffer.cli.run import run

if TYPE_CHECKING:
    from whiztap.analyzer.probe.model import CaseResult, ProbeReport
    from whiztap.analyzer.probe.server_plan import ServerCase

LIST_FORMATS = ("text", "markdown", "json")


@click.group("probe")
def probe_command() -> None:
    """Test a Progwhiz server or client against the spec (Rev 1.8), case by case."""


def catalogue_listing(cases: list[ServerCase], fmt: str) -> str:
    """The catalogue without running it: id, spec section and title of each case."""
    if fmt == "json":
        import json

        return json.dumps([{"id": c.id, "spec": c.spec, "title": c.title} for c in cases], indent=2) + "\n"
    if fmt == "markdown":
        rows = [f"| `{c.id}` | {c.spec} | {_cell(c.title)} |" for c in cases]
        return "\n".join(["| case | spec section | what it checks |", "|---|---|---|", *rows]) + "\n"
    width = max(len(c.id) for c in cases)
    return "".join(f"{c.id.ljust(width)}  {c.spec}: {c.title}\n" for c in cases)


def _cell(text: str) -> str:
    return text.replace("|", "\\|")


@probe_command.command("server")
@click.argument("address", type=Address(what="the server address"), metavar="HOST:PORT", required=False)
@click.option("--password", "-p", envvar="WHIZTAP_PASSWORD", default=None,
              help="The Winsock password (default: $WHIZTAP_PASSWORD, which ps does not show).")
@click.option("--cases", "patterns", multiple=True, metavar="GLOB",
              help="Run only the cases whose id matches (repeatable), e.g. 'handshake.*'.")
@click.option("--seed", type=int, default=0, show_default=True, help="Chooses the stray bytes the cases send.")
@click.option("--record", "record_dir", metavar="DIR",
              help="Record the run into DIR/probe-server.mcap, a connection per case.")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="text", show_default=True,
              help="The report's format.")
@click.option("-o", "--output", metavar="FILE", help="Write the report to FILE (default: standard output).")
@force_option
@click.option("--list", "list_only", is_flag=True,
              help="Print the catalogue (id, spec section, title) and exit, without a server.")
@click.option("-q", "--quiet", is_flag=True, help="No progress on the terminal.")
@click.option("-v", "--verbose", is_flag=True, help="A line per case on stderr as it ends.")
def server_command(address: tuple[str, int] | None, password: str | None, patterns: tuple[str, ...], seed: int,
                   record_dir: str | None, fmt: str, output: str | None, force: bool, list_only: bool,
                   quiet: bool, verbose: bool) -> None:
    """Probe the Progwhiz server at HOST:PORT: every case of the catalogue on
    its own connection, judged by whiztap's rules.

    The handshake is found by itself: Winsock when the server says
    'sendchkpass' on connect (give --password), VPN otherwise.  Exit status 0
    when no case failed, 1 when one did, 2 when the probe could not run.
    """
    from whiztap.analyzer.probe.server_cases import catalogue, select

    cases = select(catalogue(), patterns)
    if not cases:
        fail(f"--cases {' '.join(patterns)} matches no case; 'whiztap probe server --list' lists them")
    if list_only:
        if fmt not in LIST_FORMATS:
            fail(f"--list prints {', '.join(LIST_FORMATS)}, not {fmt}")
        with output_stream(output, force) as out:
            out.write(catalogue_listing(cases, fmt))
        return
    if address is None:
        fail("give the server's address, HOST:PORT (or --list for the catalogue)")
    check_output(output, force=force)
    report = run(_probe(address, password, cases, seed, record_dir, quiet, verbose))
    _write(report, fmt, output, force)
    sys.exit(report.exit_status)


async def _probe(address: tuple[str, int], password: str | None, cases: list[ServerCase], seed: int,
                 record_dir: str | None, quiet: bool, verbose: bool) -> ProbeReport:
    from whiztap.sniffer.probe.server_run import ProbeError, ProbeSettings, probe_server

    settings = ProbeSettings(address[0], address[1], None if password is None else password.encode(), seed,
                             record_dir)
    progress = sys.stderr.isatty() and not quiet

    def on_case(index: int, result: CaseResult) -> None:
        if verbose:
            click.echo(f"{result.verdict.upper():4}  {result.id}", err=True)
        elif progress:
            click.echo(f"\r\x1b[K[{index + 1}/{len(cases)}] {result.id}", err=True, nl=False)

    try:
        report = await probe_server(settings, cases, on_case)
    except ProbeError as e:
        fail(str(e))
    finally:
        if progress and not verbose:
            click.echo("\r\x1b[K", err=True, nl=False)
    return report


def _write(report: ProbeReport, fmt: str, output: str | None, force: bool) -> None:
    from whiztap.analyzer.errors import WhiztapError
    from whiztap.analyzer.probe.report import render

    colour = fmt == "text" and (output is None or output == "-") and sys.stdout.isatty()
    try:
        text = render(report, fmt, colour=colour)
    except WhiztapError as e:  # the recording could not be read back for the HTML report
        fail(f"cannot read the recording for the report: {e}")
    with output_stream(output, force) as out:
        out.write(text)


probe_command.add_command(probe_client_command)
