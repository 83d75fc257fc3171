"""Salvage a recording whose writer died: ``NAME.mcap.part`` to ``NAME.mcap``.

A crashed recorder leaves every chunk it flushed (it flushes at least once a
second), followed perhaps by half a chunk and no index.  mcap's seeking reader
starts from the footer and so finds nothing in such a file; its non-seeking
reader reads chunk after chunk from the start and stops with an error at the
cut.  Recovery copies everything it yields (schemas, channels, messages,
metadata, attachments) into a new file through the normal Writer, which adds
the index.  The original is never modified.
"""

from __future__ import annotations

import os
import struct
from dataclasses import dataclass

from mcap.exceptions import McapError
from mcap.records import Attachment, Channel, Metadata, Schema
from mcap.stream_reader import StreamReader
from mcap.records import Message as McapMessage
from mcap.writer import Writer

from analyzer.output_rule import OutputRefused, check_output
from analyzer.recording import PROFILE


class RecoverError(Exception):
    """Recovery could not run; one line for the user."""


@dataclass(frozen=True)
class RecoverResult:
    output: str
    messages: int
    complete: bool  # False when the input ended mid-record (the usual crash)


def default_output(path: str) -> str:
    if path.endswith(".part"):
        return path[: -len(".part")]
    stem, _ = os.path.splitext(path)
    return stem + ".recovered.mcap"


def recover(path: str, output: str | None = None, *, force: bool = False) -> RecoverResult:
    """Copy every readable record of ``path`` into a new, indexed MCAP file."""
    if not os.path.isfile(path):
        raise RecoverError(f"{path}: no such file" if not os.path.exists(path) else f"{path}: not a file")
    output = output or default_output(path)
    try:
        check_output(output, [path], force=force)
    except OutputRefused as e:
        raise RecoverError(str(e)) from None
    try:
        source = open(path, "rb")  # noqa: SIM115 - closed below
    except OSError as e:
        raise RecoverError(f"cannot read {path}: {e.strerror}") from None
    partial = output + ".recovering"  # not .part: that is usually the input
    try:
        with source, open(partial, "wb") as sink:
            messages, complete = _copy(source, sink, path)
        os.replace(partial, output)
    except OSError as e:
        _remove(partial)
        raise RecoverError(f"cannot write {output}: {e.strerror}") from None
    except RecoverError:
        _remove(partial)
        raise
    return RecoverResult(output, messages, complete)


def _remove(path: str) -> None:
    try:
        os.unlink(path)
    except OSError:
        pass


def _copy(source, sink, path: str) -> tuple[int, bool]:  # noqa: ANN001 - binary files
    writer = Writer(sink)
    schemas: dict[int, int] = {}
    channels: dict[int, int] = {}
    messages = 0
    complete = True
    started = False
    try:
        for record in StreamReader(source, validate_crcs=True).records:
            if not started:
                writer.start(PROFILE, "whiztap recover")
                started = True
            if isinstance(record, Schema):
                if record.id not in schemas:
                    schemas[record.id] = writer.register_schema(record.name, record.encoding, record.data)
            elif isinstance(record, Channel):
                if record.id not in channels:
                    channels[record.id] = writer.register_channel(
                        record.topic, record.message_encoding, schemas.get(record.schema_id, 0), record.metadata)
            elif isinstance(record, McapMessage):
                channel = channels.get(record.channel_id)
                if channel is not None:
                    writer.add_message(channel, record.log_time, record.data, record.publish_time, record.sequence)
                    messages += 1
            elif isinstance(record, Metadata):
                writer.add_metadata(record.name, record.metadata)
            elif isinstance(record, Attachment):
                writer.add_attachment(record.create_time, record.log_time, record.name,
                                      record.media_type, record.data)
    except (McapError, struct.error, EOFError, ValueError) as e:
        # the cut: a half-written record, or a chunk whose CRC no longer matches
        if not started:
            raise RecoverError(f"{path} is not an MCAP file or holds nothing readable ({e})") from None
        complete = False
    if not started:
        raise RecoverError(f"{path} is empty")
    writer.finish()
    return messages, complete
