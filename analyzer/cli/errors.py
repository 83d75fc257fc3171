"""The one kind of error a command shows: one line on stderr, exit status 2.

Libraries raise their own exception types (all ``WhiztapError``); commands turn
them into this, adding what the library does not know (which option, which
file), and the root turns any the commands did not catch into the same line.
"""

from __future__ import annotations

from typing import IO, Any, NoReturn

import click

from whiztap.analyzer.errors import WhiztapError

EXIT_USAGE = 2  # bad input, unreadable file, unreachable peer, interrupted


class CommandFailed(click.ClickException, WhiztapError):
    """A problem the user can fix, as a command says it: printed as one line,
    exit status 2."""

    exit_code = EXIT_USAGE

    def show(self, file: IO[Any] | None = None) -> None:
        warn(self.format_message())


def warn(message: str) -> None:
    """A line for the user on stderr.  Messages name files and quote what
    files and peers said, so control characters are shown, never obeyed."""
    from whiztap.analyzer.protocol.text import printable

    click.echo(f"whiztap: {printable(message)}", err=True)


def fail(message: str) -> NoReturn:
    raise CommandFailed(message)
