"""``whiztap rules`` and ``whiztap decode``: the rules, and frames typed as text checked against them."""

from __future__ import annotations

import os
import re
import sys
from collections.abc import Sequence
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.params import checksum_rule_option, limits_from, limits_options

if TYPE_CHECKING:
    from whiztap.analyzer.protocol.observations import Direction, Event
    from whiztap.analyzer.protocol.rules import Violation
    from whiztap.analyzer.protocol.session import Limits


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
        click.echo(f"{r.id:28} {r.severity!s:8} {r.section:30} {r.summary}")


_PATH_LIKE = re.compile(r"^(?!(c2s |s2c )?[rcs]r1-).*(/|\.[A-Za-z][A-Za-z0-9]{0,4}$)", re.DOTALL)
"""A folder or a file extension in it, and no frame header at its start: meant as a file."""


@click.command("decode")
@click.argument("inputs", nargs=-1, metavar="[FRAME | FILE | -]...")
@click.option("--frame", "-f", "frames", multiple=True, metavar="TEXT",
              help="A frame, even one that looks like a file name; repeatable.")
@click.option("--dir", "direction", type=click.Choice(["c2s", "s2c", "auto"]), default="auto", show_default=True,
              help="Which side sent each frame; auto takes rr1 frames and passwords as the client's.")
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@limits_options
def decode_command(inputs: tuple[str, ...], frames: tuple[str, ...], direction: str, checksum_rule: str,
                   answer_timeout: float, max_frame: int, max_image: int) -> None:
    """Decode and check frames written as escaped text (\\x0c for a raw byte).

    \b
    FRAME  one frame, judged on its own: its syntax, fields, direction and
           checksum; what only a session can tell (the handshake, the
           channel map, pairing) is not judged
    FILE   a file of frames, one per line; '-' (or a pipe, when nothing
           else is given) for standard input.  The lines run through one
           session, so handshake order, pairing and the channel map are
           checked as on a live connection (one line alone: as a FRAME)
    \b
    A frame or line may begin with 'c2s ' or 's2c ' to say who sent it.  An
    argument is a FILE when it names one; one with a '/' or a file extension
    that names none is refused (-f takes it as a frame).  Exit status 1 when
    a rule of error severity was broken.
    """
    limits = limits_from(answer_timeout, max_frame, max_image)
    if not inputs and not frames and sys.stdin is not None and not sys.stdin.isatty():
        inputs = ("-",)  # piped in: read it, as filters do
    if not inputs and not frames:
        fail("nothing to decode: give a frame (whiztap decode 'rr1-24--0--0-ss1'), a file of frames "
             "one per line, or '-' for standard input")
    worst = 0
    alone: list[str] = []
    for arg in inputs:
        if arg == "-" or os.path.isfile(arg):
            worst = max(worst, _session(arg, _read_lines(arg), direction, checksum_rule, limits))
        elif os.path.isdir(arg):
            fail(f"{arg} is a folder: decode takes frames, or a file of frames one per line")
        elif _PATH_LIKE.search(arg):
            fail(f"cannot read {arg}: no such file (to decode it as a frame, give it with -f)")
        else:
            alone.append(arg)
    alone += frames
    if alone:
        worst = max(worst, _lone_frames(alone, direction, checksum_rule, limits))
    from whiztap.analyzer.protocol.rules import Severity

    if worst >= Severity.ERROR:
        sys.exit(1)


def _read_lines(source: str) -> list[str]:
    try:
        with click.open_file(source, "rb") as f:
            return f.read().decode("utf-8").splitlines()
    except OSError as e:
        fail(f"cannot read {source}: {e.strerror}")
    except UnicodeDecodeError:
        fail(f"{source} is not text: decode takes frames as escaped text, one per line "
             f"(\\x0c for a raw byte); for a recording use 'whiztap cat'")


def _sender(text: str, direction: str) -> tuple[Direction, str]:
    """Who sent a frame written as ``text`` (its 'c2s '/'s2c ' prefix, else
    --dir, else a guess from its first bytes), and the frame without the prefix."""
    from whiztap.analyzer.protocol.observations import Direction, sender_of

    side, _, rest = text.partition(" ")
    if side in ("c2s", "s2c"):
        return Direction(side), rest
    if direction != "auto":
        return Direction(direction), text
    server = sender_of(text.encode("utf-8", "replace")) is Direction.S2C  # by its opening
    return (Direction.S2C if server else Direction.C2S), text


def _bytes(text: str) -> bytes:
    """The bytes escaped ``text`` stands for; a byte that is no UTF-8 in an
    argument (which Python hands over as a surrogate) is that byte."""
    from whiztap.analyzer.protocol.text import printable, unescape

    try:
        return unescape(text.encode("utf-8", "surrogateescape").decode("utf-8", "backslashreplace"))
    except UnicodeEncodeError:
        fail(f"{printable(text)} holds a character that is no byte (a lone surrogate): write bytes as \\xNN")


def _session(source: str, lines: list[str], direction: str, checksum_rule: str, limits: Limits) -> int:
    """The lines of one file through one session; the worst severity broken (0: none)."""
    from whiztap.analyzer.protocol.text import plural

    frames = [line for line in lines if line.strip() and not line.lstrip().startswith("#")]
    if not frames:
        where = "standard input" if source == "-" else source
        fail(f"nothing to decode: {where} holds no frame (one per line; '#' starts a comment)")
    if len(frames) == 1:
        return _lone_frames(frames, direction, checksum_rule, limits)  # one frame is no session
    session = limits.session(checksum_rule)
    worst = 0
    t = 0
    for line in frames:
        dir_, text = _sender(line, direction)
        t += 1_000_000
        for event in session.receive(dir_, _bytes(text), t):
            worst = max(worst, _print_event(event))
    for event in session.close(t + 1):
        worst = max(worst, _print_event(event))
    total = sum(session.violation_counts.values())
    name = "" if source == "-" else f"{source}: "
    click.echo(f"{name}mode {session.mode}, handshake {session.handshake_outcome}, {plural(total, 'violation')}")
    return worst


def _lone_frames(texts: list[str], direction: str, checksum_rule: str, limits: Limits) -> int:
    """Each frame judged on its own (``frame_alone``, as the proxy's stages
    and the TUI's editor judge one); the worst severity broken (0: none)."""
    from whiztap.analyzer.protocol.frame_text import frame_alone
    from whiztap.analyzer.protocol.text import plural

    worst = total = 0
    for text in texts:
        dir_, frame = _sender(text, direction)
        data = _bytes(frame)
        if not data:
            fail("an empty frame: give its text, such as rr1-24--0--0-ss1")
        observations, whole = frame_alone(data, dir_, checksum_rule, limits.max_frame, limits.max_image)
        for o in observations:
            worst = max(worst, _print_event(o))
            total += len(o.violations)
        worst = max(worst, _print_violations(whole))
        total += len(whole)
    click.echo(f"{plural(len(texts), 'frame')}, each judged on its own: {plural(total, 'violation')}")
    return worst


def _print_event(event: Event) -> int:
    """Print one event; return the highest severity among its violations (0 if none)."""
    from whiztap.analyzer.protocol.describe import meaning
    from whiztap.analyzer.protocol.observations import LateViolation
    from whiztap.analyzer.protocol.text import escape, printable

    violations: tuple[Violation, ...]
    if isinstance(event, LateViolation):
        violations = (event.violation,)
    else:
        click.echo(printable(f"{event.direction} {event.item.kind:10} {escape(event.item.raw)}  ->  {meaning(event)}"))
        violations = event.violations
    return _print_violations(violations)


def _print_violations(violations: Sequence[Violation]) -> int:
    from whiztap.analyzer.protocol.text import printable

    for v in violations:
        click.echo(printable(f"  ! {v.rule_id} ({v.severity}): {v.detail}"))
    return max((v.severity for v in violations), default=0)
