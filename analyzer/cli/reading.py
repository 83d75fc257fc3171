"""How commands find and read the recordings a user names: one line and exit
status 2 for anything that is not a readable recording, with what to do."""

from __future__ import annotations

import shlex
from collections.abc import Iterator
from pathlib import Path
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.cli.errors import fail, warn
from whiztap.analyzer.cli.progress import ByteProgress

if TYPE_CHECKING:
    from whiztap.analyzer.recording.sets import RecordingSet
    from whiztap.analyzer.traffic import TrafficEvent


def recordings(inputs: tuple[str, ...], urls: bool = False) -> list[RecordingSet]:
    """What the user named, as recordings (a split one's parts together);
    a line on stderr for each whose parts are not all there.  ``urls``: names
    like ``s3://...`` are URLs read through fsspec (``analyze``)."""
    from whiztap.analyzer.recording.sets import RecordingInputError, find_recordings

    try:
        found = find_recordings(inputs, urls)
    except RecordingInputError as e:
        fail(str(e))
    for recording in found:
        warning = recording.warning()
        if warning:
            warn(warning)
    return found


def scan_recording(recording: RecordingSet | Path | str,
                   progress: ByteProgress | None = None) -> Iterator[TrafficEvent]:
    """The traffic events of a recording (a ``RecordingSet``, or one path) in
    recorded order, across its parts.

    Raises ``click`` errors with one-line messages for files that are not
    readable recordings, end before their footer, or fail to read (a URL's
    connection lost in the middle).
    """
    from whiztap.analyzer.recording.remote import open_part
    from whiztap.analyzer.recording.sets import PartError, RecordingSet, scan_set

    if not isinstance(recording, RecordingSet):
        recording = RecordingSet((Path(recording),))
    try:
        yield from scan_set(recording, progress.open if progress is not None else open_part)
    except OSError as e:
        fail(f"{recording}: cannot read ({e.strerror or e})")
    except PartError as e:
        from whiztap.analyzer.recording.sets import being_written

        if not isinstance(e.path, Path):  # a URL: what the reader said is all there is to say
            fail(str(e))
        if being_written(e.path):
            fail(f"{e.path} is being written by a running recorder; analyze it once the recorder has finished, "
                 f"or watch it grow: whiztap cat --follow {shlex.quote(str(e.path))}")
        if e.truncated or e.path.name.endswith(".part"):
            fail(f"{e}; it looks like a recording that was cut short; "
                 f"to turn it into a complete file: whiztap recover {shlex.quote(str(e.path))}")
        fail(str(e))


def one_recording(inputs: tuple[str, ...]) -> RecordingSet:
    """The one recording a command reads: a file, a split one's first part, its
    folder or a glob (expanded by the shell or not)."""
    from whiztap.analyzer.recording.sets import RecordingInputError, find_one

    try:
        found = find_one(inputs)
    except RecordingInputError as e:
        fail(f"{e} (see '{click.get_current_context().command_path} --help')")
    warning = found.warning()
    if warning:
        warn(warning)
    return found
