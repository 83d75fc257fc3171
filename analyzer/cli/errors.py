"""The one kind of error a command shows: one line on stderr, exit status 2.

Libraries raise their own exception types; commands turn them into this.
"""

from __future__ import annotations

from typing import NoReturn

import click

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
