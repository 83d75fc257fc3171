"""``whiztap probe client``: whiztap plays the server, a client under test runs once per case.

Imports stay light at module level (``whiztap probe --help`` loads this
module); the runner, which brings in the simulator, is imported when it runs.
"""

from __future__ import annotations

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream
from whiztap.analyzer.cli.params import force_option
from whiztap.analyzer.probe.client_cases import ClientCase, catalogue, catalogue_table, select
from whiztap.analyzer.probe.model import ProbeReport
from whiztap.analyzer.probe.report import FORMATS
from whiztap.sniffer.cli.run import run
from whiztap.sniffer.sim.robot import DEFAULT_PASSWORD

DEFAULT_TIMEOUT = 10.0  # (the runner's; repeated here so --help needs no runner)


@click.command("client")
@click.option("--run", "command", metavar="'CMD {host} {port}'",
              help="The client to test, started once per case: {host} and {port} are filled in "
                   "(also WHIZTAP_PROBE_HOST, WHIZTAP_PROBE_PORT, WHIZTAP_PROBE_CASE and, in winsock mode, "
                   "WHIZTAP_PROBE_PASSWORD in its environment).")
@click.option("--cases", "patterns", multiple=True, metavar="GLOB",
              help="Run only the cases whose id matches (repeatable, or comma-separated); --list shows them.")
@click.option("--seed", type=int, default=0, show_default=True,
              help="Seeds the sensor signals and the stray bytes.")
@click.option("--password", default=DEFAULT_PASSWORD, show_default=True,
              help="The password the played server takes (winsock mode); the client gets it in "
                   "WHIZTAP_PROBE_PASSWORD, never on its command line.")
@click.option("--mode", type=click.Choice(["winsock", "vpn"]), default="winsock", show_default=True,
              help="The handshake the played server asks for.")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=DEFAULT_TIMEOUT,
              show_default=True, metavar="S",
              help="Seconds a client may take per case before it is killed (its own timeouts must be shorter).")
@click.option("--format", "fmt", type=click.Choice(FORMATS), default="text", show_default=True,
              help="Report format.")
@click.option("-o", "--output", type=click.Path(dir_okay=False, allow_dash=True), default=None,
              help="Write the report to this file ('-': standard output, the default).")
@force_option
@click.option("--list", "list_cases", is_flag=True, help="List the cases (id, spec section, title) and exit.")
def probe_client_command(command: str | None, patterns: tuple[str, ...], seed: int, password: str, mode: str,
                         timeout: float, fmt: str, output: str | None, force: bool, list_cases: bool) -> None:
    """Test a Progwhiz client: whiztap plays the server, the simulator's behaviour
    with adversarial schedules (answers cut into pieces, slow, refused,
    closed, idle, garbage, the largest camera picture), and starts the client
    once per case.  A case fails on the client's own spec violations, on a
    client that hangs (killed with its process group), crashes (a traceback
    or a signal), or fails against a server that keeps the spec.

    Exit status 0 when every case passed or was skipped, 1 when one failed,
    2 when the run could not happen.
    """
    cases = _chosen(patterns)
    if list_cases:
        click.echo(catalogue_table(cases), nl=False)
        return
    if not command or not command.strip():
        fail("--run: give the client's command, e.g. --run 'myclient {host} {port}' (--list needs none)")
    if mode == "winsock" and not password:
        fail("--password: winsock mode needs a non-empty password")
    check_output(output, force=force)
    report = run(_probe(command, mode, password, seed, timeout, cases))
    with output_stream(output, force) as out:
        out.write(render_report(report, fmt, colour=fmt == "text" and out.isatty()))
    raise SystemExit(report.exit_status)


def _chosen(patterns: tuple[str, ...]) -> list[ClientCase]:
    globs = [p.strip() for pattern in patterns for p in pattern.split(",") if p.strip()]
    chosen = select(catalogue(), globs)
    if not chosen:
        fail(f"--cases: no case matches {', '.join(globs)}; --list shows them")
    return chosen


async def _probe(command: str, mode: str, password: str, seed: int, timeout: float,
                 cases: list[ClientCase]) -> ProbeReport:
    from whiztap.sniffer.probe.client_run import ClientProbe, ProbeClientError, probe_client
    from whiztap.sniffer.sim.robot import ServerMode

    try:
        return await probe_client(ClientProbe(command, ServerMode(mode), password, seed, timeout), cases)
    except ProbeClientError as e:
        fail(str(e))


def render_report(report: ProbeReport, fmt: str, colour: bool) -> str:
    """The report in ``fmt``, in the shapes ``probe server`` prints (no
    recording: the HTML report lists the cases without frames)."""
    from whiztap.analyzer.probe.report import render

    return render(report, fmt, colour=colour)

