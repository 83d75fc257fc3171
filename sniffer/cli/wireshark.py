"""``whiztap export`` and ``whiztap wireshark-dissector``: recordings for
Wireshark and tshark, and the dissector that reads them (docs/wireshark.md)."""

from __future__ import annotations

import contextlib
import os
import sys
from collections.abc import Iterator
from typing import IO

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, output_stream, say
from whiztap.analyzer.cli.params import checksum_rule_option, force_option
from whiztap.analyzer.cli.reading import one_recording
from whiztap.analyzer.protocol.text import plural


@contextlib.contextmanager
def _binary_output(path: str, force: bool) -> Iterator[IO[bytes]]:
    """Standard output for '-' (a reader that goes away ends the command
    quietly), else a new file, removed again if the export fails."""
    if path == "-":
        try:
            yield sys.stdout.buffer
            sys.stdout.buffer.flush()
        except BrokenPipeError:
            from whiztap.analyzer.recording.stdout import drop_stdout

            drop_stdout()
            sys.exit(0)
        return
    from whiztap.analyzer.recording.output_rule import create_mode

    try:
        f = open(path, create_mode(path, force) + "b")  # closed below
    except OSError as e:
        fail(f"cannot write {path}: {e.strerror}")
    try:
        with f:
            yield f
    except BaseException:
        os.unlink(path)
        raise


@click.command("export")
@click.option("--pcap", "pcap", required=True, type=click.Path(dir_okay=False), metavar="OUT.pcapng",
              help="Write the connections as TCP packets to this pcapng file ('-': standard output).")
@click.argument("recording", nargs=-1, required=True, type=click.Path(dir_okay=True))
@force_option
@click.option("-q", "--quiet", is_flag=True, help="Print nothing but errors.")
def export_command(pcap: str, recording: tuple[str, ...], force: bool, quiet: bool) -> None:
    """Write a recording's connections as TCP packets, for Wireshark and tshark.

    Each connection is one TCP conversation between the recorded client and
    server addresses: the handshake, one segment per recorded read at its
    time (reads over 65,495 bytes in several), and the close.  Bytes missing
    from the recording are a jump in the sequence numbers.  Passwords stay as
    recorded (masked unless recorded with --keep-secrets).  'whiztap capture
    --pcap' of the file gives back the same byte streams.  See
    docs/wireshark.md.
    """
    found = one_recording(recording)
    check_output(pcap, found.parts, force=force)
    from whiztap.sniffer.wireshark.export import ExportError, export_pcapng

    try:
        with _binary_output(pcap, force) as out:
            summary = export_pcapng(found, out)
    except ExportError as e:
        fail(str(e))
    if not quiet and pcap != "-":
        say(f"exported {plural(summary.connections, 'connection')}, {plural(summary.packets, 'packet')} "
            f"({plural(summary.bytes, 'byte')} of payload) into {pcap}")


@click.command("wireshark-dissector")
@click.option("-o", "--output", default="-", show_default=True, type=click.Path(dir_okay=False),
              help="Where to write the Lua dissector ('-': standard output).")
@click.option("--port", type=click.IntRange(0, 65535), default=5000, show_default=True,
              help="The TCP port it dissects as Progwhiz by default (a preference; 0: none, only the heuristic).")
@checksum_rule_option("Set Configuration checksum rule it checks by default (a preference; see 'whiztap rules').",
                      show_default=True)
@click.option("--answer-timeout", type=click.FloatRange(min=0.001), default=5.0, show_default=True,
              metavar="SECONDS", help="How long a request may wait for its answer (a preference).")
@force_option
def dissector_command(output: str, port: int, checksum_rule: str, answer_timeout: float, force: bool) -> None:
    """Write a Wireshark Lua dissector generated from whiztap's own message table.

    Every message kind and field by name (progwhiz.channel == 12), frames
    reassembled across TCP segments, the meaning that depends on the channel
    map where it can be known, and every rule violation as expert info with
    its rule id.  A heuristic finds Progwhiz on any port.  Load it with
    'wireshark -X lua_script:progwhiz.lua' or copy it into Wireshark's Lua
    plugins folder.  See docs/wireshark.md.
    """
    check_output(output, force=force)
    from whiztap.sniffer.wireshark.dissector import DissectorError, generate

    try:
        text = generate(port, checksum_rule, round(answer_timeout * 1000))
    except DissectorError as e:
        fail(str(e))
    with output_stream(output, force) as out:
        out.write(text)
