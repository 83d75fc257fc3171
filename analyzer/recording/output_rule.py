"""The one rule for every file whiztap writes: never an input, and never an
existing file unless the user said ``--force``.

A mistyped ``-o`` must not cost a recording.  Every command that writes a file
(analyze, cat, replay, record, capture, recover, tui, demo, client's camera)
checks its output here before it starts, and libraries raise ``OutputRefused``
for their callers to show as one line.

An input is recognised as the same file, not the same name: through symbolic
links, hard links and relative paths (device and inode).  A recording is
written as ``NAME.part`` and renamed when finished, so both names are checked.
An existing output that is not a regular file (``/dev/null``, a FIFO, a
terminal) holds nothing to lose and is written to as it is.
"""

from __future__ import annotations

import os
import shlex
import stat
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

from whiztap.analyzer.errors import WhiztapError

if TYPE_CHECKING:
    from whiztap.analyzer.recording.remote import RemotePart

_NEVER = "an input is never written over, even with --force"


class OutputRefused(WhiztapError):
    """The output may not be written; the message is one line for the user.
    ``existing``: the file in the way when that is the only reason (--force
    would write over it); None when the output is an input."""

    def __init__(self, message: str, existing: str | None = None) -> None:
        super().__init__(message)
        self.existing = existing


def check_output(output: str, inputs: Iterable[str | Path | RemotePart] = (), *, force: bool = False,
                 recording: bool = False, split: bool = False) -> None:
    """Raise ``OutputRefused`` when writing ``output`` would write over one of
    ``inputs`` (always refused) or over an existing file (refused unless
    ``force``).  ``recording``: ``output`` is a recording, written as
    ``NAME.part`` first; ``split``: in numbered parts, the first of which is
    checked here (later parts are checked by the writer as it creates them)."""
    first = _first_file(output, split) if recording else output
    targets = [first, first + ".part"] if recording else [first]
    named = [str(p) for p in inputs]
    identities = {_identity(p): p for p in named}
    identities.pop(None, None)
    names = {os.path.abspath(p): p for p in named}  # an input not there yet: read once it is
    for target in targets:
        found = identities.get(_identity(target)) or names.get(os.path.abspath(target))
        if found is None:
            continue
        if target != first:
            raise OutputRefused(f"{first} is written as {target} until it is finished, and {target} is an "
                                f"input; choose another output name ({_NEVER})")
        what = "an input" if os.path.abspath(found) == os.path.abspath(target) else \
            f"the same file as the input {found}"
        raise OutputRefused(f"{target} is {what}; choose another output name ({_NEVER})")
    if force:
        return
    if occupied(first):
        raise OutputRefused(f"{first} exists; use --force to overwrite it or -o to choose another name", first)
    if recording and occupied(first + ".part"):
        raise OutputRefused(f"{first}.part exists (a recording cut short?); use --force to overwrite it, "
                            f"or save it first: whiztap recover {shlex.quote(first + '.part')}", first + ".part")


def occupied(path: str) -> bool:
    """Whether writing ``path`` would replace something: an existing name that
    is not a device, FIFO or socket (a dangling link counts: following it
    would create a file where the user did not say)."""
    try:
        mode = os.stat(path).st_mode
    except OSError:  # nothing there (or nothing reachable: writing it fails with its own message)
        return os.path.islink(path)
    return not (stat.S_ISCHR(mode) or stat.S_ISBLK(mode) or stat.S_ISFIFO(mode) or stat.S_ISSOCK(mode))


def create_mode(path: str, force: bool) -> str:
    """How to open an output that passed ``check_output``: "w" when forced or
    for a device or FIFO (nothing to lose), else "x", so that a file which
    appeared since the check is still not written over."""
    return "w" if force or (os.path.exists(path) and not occupied(path)) else "x"


def _first_file(output: str, split: bool) -> str:
    # imported here: every command checks its output first thing, and sets
    # brings the recording reader (40 ms of imports), which only a recording's name needs
    from whiztap.analyzer.recording.sets import part_path

    return part_path(output, 1 if split else None)


def _identity(path: str | Path) -> tuple[int, int] | None:
    """(device, inode) of the regular file a name leads to; None for anything
    else (no file; a terminal that is both standard input and output)."""
    try:
        s = os.stat(path)
    except OSError:
        return None
    return (s.st_dev, s.st_ino) if stat.S_ISREG(s.st_mode) else None
