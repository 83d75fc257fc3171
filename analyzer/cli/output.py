"""Where commands write: the output rule as one-line errors, standard output
that may go away, and status lines that quote what peers said."""

from __future__ import annotations

import contextlib
import sys
from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import IO, TYPE_CHECKING, NoReturn

import click

from whiztap.analyzer.cli.errors import fail

if TYPE_CHECKING:
    from whiztap.analyzer.recording.remote import RemotePart


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
        f = open(output, create_mode(output, force), encoding="utf-8")  # closed below
    except FileExistsError:
        check_output(output, force=False)  # it appeared since the check: refused in the rule's words
        raise  # and went again at once: the unexpected-error line says so
    except OSError as e:
        fail(f"cannot write {output}: {e.strerror}")
    with f:
        yield f


def check_output(output: str | None, inputs: Iterable[str | Path | RemotePart] = (), *, force: bool,
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


def recording_output(output: str | None) -> None:
    """A recording (MCAP) is written as NAME.part and renamed when finished, so
    a crash leaves something 'whiztap recover' can save: standard output cannot
    be one.  Refuse '-' in one line rather than make a file named '-'."""
    if output == "-":
        fail("-o -: a recording is written to a file (as NAME.part until it is finished), "
             "not to standard output; give a file name")


def say(line: str) -> None:
    """Print a status line for the user (they quote clients, servers and files:
    control characters are shown, never obeyed).  Once standard output is gone
    print nothing more: what the command is doing (finishing a recording)
    still has to be done."""
    from whiztap.analyzer.protocol.text import printable
    from whiztap.analyzer.recording.stdout import drop_stdout

    try:
        click.echo(printable(line))
    except OSError:  # a closed pipe (EPIPE) or terminal (EIO)
        drop_stdout()


def _pipe_closed() -> NoReturn:
    """Standard output's reader left: stop writing, say nothing, succeed."""
    from whiztap.analyzer.recording.stdout import drop_stdout

    drop_stdout()
    sys.exit(0)
