"""Options and parameter types every command shares: sizes, the checksum rule,
--force and the limits of the session model.

Each converts and checks what the user typed once, here; a value that does not
fit is the usual one line and exit status 2.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE

if TYPE_CHECKING:
    from whiztap.analyzer.protocol.session import Limits


class ByteSize(click.ParamType):
    """A byte count: 500000, 100k, 64M, 2G (powers of 1024)."""

    name = "BYTES"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> int:
        if isinstance(value, int):
            return value
        from whiztap.analyzer.protocol.text import parse_size

        try:
            return parse_size(str(value))
        except ValueError as e:
            self.fail(str(e), param, ctx)


class ChecksumRule(click.ParamType):
    """The name of a Set Configuration checksum rule ('whiztap rules',
    docs/protocol.md); an unknown one names the known ones."""

    name = "name"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> str:
        from whiztap.analyzer.protocol.checksum import get_rule

        try:
            return get_rule(value).name
        except ValueError as e:
            fail(str(e))


def checksum_rule_option(help: str, show_default: bool = False) -> Callable[[Callable], Callable]:
    """``--checksum-rule NAME`` (default dev-sum), checked before the command runs."""
    return click.option("--checksum-rule", type=ChecksumRule(), default=DEFAULT_CHECKSUM_RULE,
                        show_default=show_default, help=help)


force_option = click.option(
    "--force", is_flag=True,
    help="Write over an existing output file (never over an input of the command: that is refused even so).")


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


def limits_from(answer_timeout: float, max_frame: int, max_image: int) -> Limits:
    from whiztap.analyzer.protocol.framing import MIN_MAX_ITEM
    from whiztap.analyzer.protocol.session import Limits

    if max_frame < MIN_MAX_ITEM:
        fail(f"--max-frame must be at least {MIN_MAX_ITEM} bytes")
    return Limits(round(answer_timeout * 1e9), max_frame, max(max_image, max_frame))
