"""``whiztap rules`` and ``whiztap decode``: the rules, and frames typed as text checked against them."""

from __future__ import annotations

import sys

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.params import checksum_rule_option, limits_from, limits_options


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
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@limits_options
def decode_command(source: str | None, frames: tuple[str, ...], direction: str, checksum_rule: str,
                   answer_timeout: float, max_frame: int, max_image: int) -> None:
    """Decode and check frames given as escaped text, one per line.

    SOURCE is a file of lines (or - for standard input, which is also read
    when it is a pipe and nothing else is given), optionally prefixed with
    'c2s ' or 's2c '.  The lines run through one session, so handshake
    order, pairing and the channel map are checked as on a live connection.
    Exit status 1 when a rule of error severity was broken.
    """
    from whiztap.analyzer.protocol.describe import meaning
    from whiztap.analyzer.protocol.rules import Severity
    from whiztap.analyzer.protocol.observations import Direction
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
    session = limits_from(answer_timeout, max_frame, max_image).session(checksum_rule)
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
    from whiztap.analyzer.protocol.observations import LateViolation

    from whiztap.analyzer.protocol.text import printable

    if isinstance(event, LateViolation):
        violations = (event.violation,)
    else:
        click.echo(printable(f"{event.direction} {event.item.kind:10} {escape(event.item.raw)}  ->  {meaning(event)}"))
        violations = event.violations
    for v in violations:
        click.echo(printable(f"  ! {v.rule_id} ({v.severity}): {v.detail}"))
    return max((v.severity for v in violations), default=0)
