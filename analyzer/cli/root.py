"""The ``whiztap`` command line: the root group and the analyzer's own commands.

Each package contributes subcommands through the ``whiztap.commands`` entry-point
group, loaded only when named, so this module imports nothing above the analyzer
and ``whiztap --help`` stays fast.  Command modules keep heavy imports (textual,
scapy, mcap) inside their functions.
"""

from __future__ import annotations

import contextlib
import functools
import os
import sys
from collections.abc import Callable, Iterable, Iterator
from importlib.metadata import EntryPoint, entry_points
from pathlib import Path
from typing import IO, NoReturn

import click

from whiztap.analyzer import __version__

EXIT_USAGE = 2  # bad input, unreadable file, unreachable peer, interrupted


class WhiztapError(click.ClickException):
    """A problem the user can fix: printed as one line, exit status 2."""

    exit_code = EXIT_USAGE

    def show(self, file=None) -> None:  # noqa: ANN001 - click's signature
        warn(self.format_message())


def warn(message: str) -> None:
    """A line for the user on stderr.  Messages name files and quote what
    files and peers said, so control characters are shown, never obeyed."""
    from whiztap.analyzer.protocol.text import printable

    click.echo(f"whiztap: {printable(message)}", err=True)


def fail(message: str) -> NoReturn:
    raise WhiztapError(message)




class ByteSize(click.ParamType):
    """A byte count: 500000, 100k, 64M, 2G (powers of 1024)."""

    name = "BYTES"

    def convert(self, value, param, ctx):  # noqa: ANN001, ANN201 - click's signature
        if isinstance(value, int):
            return value
        from whiztap.analyzer.protocol.text import parse_size

        try:
            return parse_size(str(value))
        except ValueError as e:
            self.fail(str(e), param, ctx)


@contextlib.contextmanager
def output_stream(output: str | None, force: bool = False) -> Iterator[IO[str]]:
    """Where a command writes its text: a file, or standard output for None or
    '-'.  A reader that goes away (``| head``) ends the command quietly, status 0.
    The file is created new unless ``force`` (``check_output`` said why it may be
    written; a file that appeared since is still not written over)."""
    if output is None or output == "-":
        try:
            yield sys.stdout
            sys.stdout.flush()
        except BrokenPipeError:
            _pipe_closed()
        return
    from whiztap.analyzer.recording.output_rule import create_mode

    try:
        f = open(output, create_mode(output, force), encoding="utf-8")  # noqa: SIM115 - closed below
    except FileExistsError:
        fail(f"{output} exists; use --force to overwrite it or -o to choose another name")
    except OSError as e:
        fail(f"cannot write {output}: {e.strerror}")
    with f:
        yield f


def check_output(output: str | None, inputs: Iterable[str | Path] = (), *, force: bool,
                 recording: bool = False, split: bool = False) -> None:
    """The rule for every file a command writes (whiztap.analyzer.recording.output_rule): never
    one of its inputs, never an existing file unless --force; one line and exit
    status 2 otherwise.  Standard output (no -o, or '-') is always fine for
    text, never for a recording."""
    from whiztap.analyzer.recording.output_rule import OutputRefused
    from whiztap.analyzer.recording.output_rule import check_output as check

    if recording:
        recording_output(output)
    if output is None or output == "-":
        return
    try:
        check(output, inputs, force=force, recording=recording, split=split)
    except OutputRefused as e:
        fail(str(e))


force_option = click.option(
    "--force", is_flag=True,
    help="Write over an existing output file (never over an input of the command: that is refused even so).")


def recording_output(output: str | None) -> None:
    """A recording (MCAP) is written as NAME.part and renamed when finished, so
    a crash leaves something 'whiztap recover' can save: standard output cannot
    be one.  Refuse '-' in one line rather than make a file named '-'."""
    if output == "-":
        fail("-o -: a recording is written to a file (as NAME.part until it is finished), "
             "not to standard output; give a file name")


def _pipe_closed() -> NoReturn:
    """Standard output's reader left: stop writing, say nothing, succeed."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, sys.stdout.fileno())  # the interpreter's last flush must not fail again
    sys.exit(0)


def limits_options(f: Callable) -> Callable:
    """``--answer-timeout``, ``--max-frame`` and ``--max-image``: the same three
    on every command that judges traffic."""
    f = click.option("--max-image", type=ByteSize(), default="32M", show_default=True,
                     help="Largest camera image taken as one item; longer ones are cut as oversize.")(f)
    f = click.option("--max-frame", type=ByteSize(), default="64k", show_default=True,
                     help="Largest item other than an image (at least 1k); bounds memory on garbage.")(f)
    return click.option("--answer-timeout", type=click.FloatRange(min=0, min_open=True), default=5.0,
                        show_default=True, metavar="SECONDS",
                        help="How long a request may wait for its answer before it is unanswered.")(f)


def limits_from(answer_timeout: float, max_frame: int, max_image: int):  # noqa: ANN201 - Limits, imported lazily
    from whiztap.analyzer.protocol.framing import MIN_MAX_ITEM
    from whiztap.analyzer.protocol.session import Limits

    if max_frame < MIN_MAX_ITEM:
        fail(f"--max-frame must be at least {MIN_MAX_ITEM} bytes")
    return Limits(round(answer_timeout * 1e9), max_frame, max(max_image, max_frame))


class _LazyGroup(click.Group):
    @functools.cached_property
    def _entry_points(self) -> dict[str, EntryPoint]:
        # once: every scan reads every installed distribution's metadata, and
        # --help asks once per command
        return {ep.name: ep for ep in entry_points(group="whiztap.commands")}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self._entry_points)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        ep = self._entry_points.get(name)
        return ep.load() if ep is not None else None


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="whiztap")
def cli() -> None:
    """Record, replay and check Progwhiz Robotics Server API (Rev 1.8) traffic."""


_NO_ARGS_IS_HELP = getattr(click.exceptions, "NoArgsIsHelpError", ())  # click >= 8.2


def main() -> None:
    try:
        cli.main(standalone_mode=False)
    except click.exceptions.Abort:
        click.echo("whiztap: interrupted", err=True)
        sys.exit(EXIT_USAGE)
    except KeyboardInterrupt:
        click.echo("whiztap: interrupted", err=True)
        sys.exit(EXIT_USAGE)
    except _NO_ARGS_IS_HELP as e:  # a bare 'whiztap': the help, as click prints it
        e.show()
        sys.exit(e.exit_code)
    except click.UsageError as e:  # one line, like every other error, rather than click's three
        command = e.ctx.command_path if e.ctx is not None else "whiztap"
        warn(f"{e.format_message()} (see '{command} --help')")
        sys.exit(e.exit_code)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    except Exception as e:  # noqa: BLE001 - the last line of defence: one line, not a traceback
        if os.environ.get("WHIZTAP_DEBUG"):
            raise
        warn(f"unexpected error: {type(e).__name__}: {e} (set WHIZTAP_DEBUG=1 to see where; please report it)")
        sys.exit(EXIT_USAGE)


@click.command("rules")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True)
def rules_command(fmt: str) -> None:
    """List every conformance rule: id, severity, spec section and summary."""
    from whiztap.analyzer.protocol.rules import RULES

    if fmt == "json":
        import json

        click.echo(json.dumps([{"id": r.id, "severity": str(r.severity), "section": r.section,
                                "summary": r.summary} for r in RULES.values()], indent=2))
        return
    for r in RULES.values():
        click.echo(f"{r.id:28} {str(r.severity):8} {r.section:30} {r.summary}")


@click.command("decode")
@click.argument("source", required=False, type=click.Path(dir_okay=False, allow_dash=True))
@click.option("--frame", "-f", "frames", multiple=True, metavar="TEXT",
              help="A frame as escaped text (\\x0c for a raw byte); repeatable.")
@click.option("--dir", "direction", type=click.Choice(["c2s", "s2c", "auto"]), default="auto", show_default=True,
              help="Which side sent each line; auto takes rr1 frames and passwords as the client's.")
@click.option("--checksum-rule", default=None, help="Set Configuration checksum rule (see 'whiztap rules').")
@limits_options
def decode_command(source: str | None, frames: tuple[str, ...], direction: str, checksum_rule: str | None,
                   answer_timeout: float, max_frame: int, max_image: int) -> None:
    """Decode and check frames given as escaped text, one per line.

    SOURCE is a file of lines (or - for standard input, which is also read
    when it is a pipe and nothing else is given), optionally prefixed with
    'c2s ' or 's2c '.  The lines run through one session, so handshake
    order, pairing and the channel map are checked as on a live connection.
    Exit status 1 when a rule of error severity was broken.
    """
    from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
    from whiztap.analyzer.protocol.describe import meaning
    from whiztap.analyzer.protocol.rules import Severity
    from whiztap.analyzer.protocol.session import Direction
    from whiztap.analyzer.protocol.text import escape, unescape

    lines = list(frames)
    if source is None and not frames and not click.get_text_stream("stdin").isatty():
        source = "-"  # piped in: read it, as filters do
    if source is not None:
        try:
            with click.open_file(source, "rb") as f:
                text = f.read().decode("utf-8")
        except OSError as e:
            fail(f"cannot read {source}: {e.strerror}")
        except UnicodeDecodeError:
            fail(f"{source} is not text: decode takes frames as escaped text, one per line "
                 f"(\\x0c for a raw byte); for a recording use 'whiztap cat'")
        lines += text.splitlines()
    if not lines:
        fail("nothing to decode: give a file, '-' for standard input, or --frame TEXT")
    limits = limits_from(answer_timeout, max_frame, max_image)
    try:
        session = limits.session(checksum_rule or DEFAULT_CHECKSUM_RULE)
    except ValueError as e:
        fail(str(e))
    worst = 0
    t = 0
    for line in lines:
        if not line.strip() or line.lstrip().startswith("#"):
            continue
        side, _, rest = line.partition(" ")
        if side in ("c2s", "s2c"):
            dir_ = Direction(side)
            line = rest
        elif direction != "auto":
            dir_ = Direction(direction)
        else:
            dir_ = Direction.S2C if line.startswith(("cr1-", "sendchkpass", "readytogo", "Failed")) or (
                line.startswith("sr1-") and not line.startswith("sr1-25--")) else Direction.C2S
        t += 1_000_000
        for event in session.receive(dir_, unescape(line), t):
            worst = max(worst, _print_event(event, meaning, escape))
    for event in session.close(t + 1):
        worst = max(worst, _print_event(event, meaning, escape))
    total = sum(session.violation_counts.values())
    click.echo(f"mode {session.mode}, handshake {session.handshake_outcome}, {total} violation(s)")
    if worst >= Severity.ERROR:
        sys.exit(1)


def _print_event(event, meaning, escape) -> int:  # noqa: ANN001 - helpers imported lazily by the caller
    """Print one event; return the highest severity among its violations (0 if none)."""
    from whiztap.analyzer.protocol.session import LateViolation

    from whiztap.analyzer.protocol.text import printable

    if isinstance(event, LateViolation):
        violations = (event.violation,)
    else:
        click.echo(printable(f"{event.direction} {event.item.kind:10} {escape(event.item.raw)}  ->  {meaning(event)}"))
        violations = event.violations
    for v in violations:
        click.echo(printable(f"  ! {v.rule_id} ({v.severity}): {v.detail}"))
    return max((v.severity for v in violations), default=0)
