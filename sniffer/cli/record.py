"""``whiztap record``, ``whiztap recover`` and ``whiztap capture``.

Heavy imports (asyncio machinery, uvloop, mcap, scapy) stay inside the command
functions so that ``whiztap --help`` does not pay for them.
"""

from __future__ import annotations

import datetime
import os
import socket
import sys
import uuid
from collections.abc import Callable, Iterable
from pathlib import Path

import click

from whiztap.analyzer.cli.root import ByteSize, check_output, fail, force_option, limits_from, limits_options, recording_output
from whiztap.analyzer.protocol.text import human_bytes

def parse_address(text: str, default_host: str | None, what: str) -> tuple[str, int]:
    """HOST:PORT, [V6]:PORT, or PORT alone when a default host is given."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "", text
    host = host.strip("[]")
    if not host:
        if default_host is None:
            fail(f"{what} must be HOST:PORT, got {text!r}")
        host = default_host
    if not port.isdigit() or int(port) > 65535:
        fail(f"{what} needs a port number 0-65535, got {text!r}")
    return host, int(port)


def say(line: str) -> None:
    """Print a line for the user.  Once standard output is gone (a closed
    terminal gives EIO, a closed pipe EPIPE) print nothing more: the recording
    still has to be finished, and the interpreter's last flush must not fail."""
    from whiztap.analyzer.protocol.text import printable  # lines quote clients and servers: shown, never obeyed

    try:
        click.echo(printable(line))
    except OSError:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
        os.close(devnull)


def clock_text(t_ns: int) -> str:
    t = datetime.datetime.fromtimestamp(t_ns / 1e9)
    return t.strftime("%H:%M:%S.%f")


def summary_lines(summary: dict, what: str) -> list[str]:
    """The lines printed when a recording ends."""
    frames, nbytes, violations = summary["frames"], summary["bytes"], summary["violations"]
    files = summary["files"]
    where = files[0] if len(files) == 1 else f"{len(files)} files ({files[0]} ... {files[-1]})" if files else "no file"
    per_dir = "; ".join(f"{d} {frames.get(d, 0)} frames {human_bytes(nbytes.get(d, 0))}" for d in ("c2s", "s2c"))
    counts = ", ".join(f"{violations.get(s, 0)} {s}" for s in ("error", "warning", "info"))
    return [f"{what} {summary['connections']} connection(s) into {where} ({human_bytes(summary['size'])}, "
            f"{summary['messages']} messages)",
            f"  {per_dir}",
            f"  violations: {counts}"]


def _run_loop(main: Callable) -> object:
    """Run a coroutine function on uvloop: an asyncio.Protocol proxy on it
    forwards about twice as fast as on the default loop."""
    import asyncio

    import uvloop

    with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
        return runner.run(main())


def base_metadata(source: str, keep_secrets: bool, checksum_rule: str, start_ns: int, **extra: object) -> dict:
    from whiztap.analyzer.recording.format import metadata_record

    start = datetime.datetime.fromtimestamp(start_ns / 1e9, datetime.timezone.utc)
    return metadata_record(source=source, start_time=start.isoformat(), start_time_ns=start_ns,
                           checksum_rule=checksum_rule, host=socket.gethostname(),
                           secrets="kept" if keep_secrets else "redacted",
                           session_id=uuid.uuid4().hex, **extra)


def check_checksum_rule(name: str | None) -> str:
    from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule

    try:
        return get_rule(name or DEFAULT_CHECKSUM_RULE).name
    except ValueError as e:
        fail(str(e))


def check_output_free(output: str, split: bool, force: bool, inputs: Iterable[str] = ()) -> None:
    """The output rule (whiztap.analyzer.recording.output_rule) for a recording: never over an
    input; not over a recording, or the ``.part`` a crashed one left (which
    'whiztap recover' could still save), unless --force."""
    check_output(output, inputs, force=force, recording=True, split=split)
    if split and not force:
        later = existing_parts(output)
        if later:
            fail(f"{later[0]} exists (a part of another recording?); "
                 f"use --force to overwrite it or -o to choose another name")


def existing_parts(output: str) -> list[str]:
    """The numbered parts of ``output`` already there (``NAME-0002.mcap``, its
    ``.part``; a link counts, even dangling): a split recording refuses them all
    at start, rather than stop when it reaches one hours later."""
    import glob
    import re

    stem, ext = os.path.splitext(output)
    ext = ext or ".mcap"
    name = re.compile(re.escape(stem) + r"-\d{4,}" + re.escape(ext) + r"(\.part)?")
    pattern = glob.escape(stem) + "-[0-9][0-9][0-9][0-9]*" + glob.escape(ext) + "*"
    return sorted(p for p in glob.glob(pattern) if name.fullmatch(p))


_FORCE = force_option

_split_options = [
    click.option("--split-size", type=ByteSize(), default=None,
                 help="Start a new numbered file when this one reaches BYTES (e.g. 100M)."),
    click.option("--split-duration", type=click.FloatRange(min=0.001), default=None, metavar="SECONDS",
                 help="Start a new numbered file every SECONDS."),
    click.option("--keep-secrets", is_flag=True,
                 help="Record the password as sent (default: '*' bytes and <redacted>)."),
    click.option("--checksum-rule", default=None, help="Set Configuration checksum rule (see 'whiztap rules')."),
    _FORCE,
]


def _with_options(options: list) -> Callable:
    def decorate(f: Callable) -> Callable:
        for option in reversed(options):
            f = option(f)
        return f
    return decorate


@click.command("record")
@click.option("--listen", default="127.0.0.1:6000", show_default=True, metavar="[HOST:]PORT",
              help="Where clients connect (port 0 picks a free one).")
@click.option("--upstream", required=True, metavar="HOST:PORT", help="The real server.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The .mcap file to write.")
@_with_options(_split_options)
@click.option("-q", "--quiet", is_flag=True,
              help="Print only the first line (it names the listening address) and errors.")
@click.option("--analyze", is_flag=True, help="Print each violation as it happens.")
@click.option("--connect-timeout", type=click.FloatRange(min=0.01), default=5.0, show_default=True,
              metavar="SECONDS", help="How long to try the upstream for each client.")
@click.option("--when-behind", type=click.Choice(["pause", "gap"]), default="pause", show_default=True,
              help="When the recording falls behind the traffic, the connections causing it: pause them "
                   "(the recording stays complete), or keep them flowing and record a gap event "
                   "with the count of bytes left out.")
@limits_options
def record_command(listen: str, upstream: str, output: str, split_size: int | None, split_duration: float | None,
                   keep_secrets: bool, checksum_rule: str | None, quiet: bool, force: bool, analyze: bool,
                   connect_timeout: float, when_behind: str, answer_timeout: float, max_frame: int,
                   max_image: int) -> None:
    """Proxy clients to the server and record every byte into an MCAP file.

    Point the client at --listen instead of the robot: every byte is forwarded
    unchanged in both directions and recorded with its receive time.  Ctrl-C or
    SIGTERM closes the connections and finishes the file.
    """
    listen_addr = parse_address(listen, "127.0.0.1", "--listen")
    upstream_addr = parse_address(upstream, None, "--upstream")
    rule = check_checksum_rule(checksum_rule)
    check_output_free(output, split_size is not None or split_duration is not None, force)
    from whiztap.sniffer.record.record_run import RecordSettings, run_record

    settings = RecordSettings(listen_addr, upstream_addr, output, split_size, split_duration, keep_secrets, rule,
                              quiet, analyze, connect_timeout, limits_from(answer_timeout, max_frame, max_image),
                              overwrite=force, when_behind=when_behind)
    error = _run_loop(lambda: run_record(settings))
    if error:
        fail(str(error))


@click.command("recover")
@click.argument("path", type=click.Path(dir_okay=False))
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Where to write (default: PATH without .part, or NAME.recovered.mcap).")
@force_option
def recover_command(path: str, output: str | None, force: bool) -> None:
    """Turn a .mcap.part left by a crash, or a damaged recording, into a valid,
    indexed MCAP file.

    Everything the recorder had flushed (all but about the last second) is
    copied into the new file; damaged chunks are skipped and said (where, how
    much), and the rest after them is kept.  The original is left as it was.
    """
    from whiztap.analyzer.recording.recover import RecoverError, recover

    recording_output(output)
    try:
        result = recover(path, output, force=force)
    except RecoverError as e:
        fail(str(e))
    click.echo(result.summary())


@click.command("capture")
@click.option("--pcap", "pcap", type=click.Path(dir_okay=False), default=None,
              help="Read a capture file (pcap or pcapng) made by tcpdump or Wireshark.")
@click.option("--iface", default=None, help="Capture live on this interface (needs root or CAP_NET_RAW).")
@click.option("--port", type=click.IntRange(1, 65535), required=True, help="The server's TCP port.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The .mcap file to write.")
@_with_options(_split_options)
@click.option("-q", "--quiet", is_flag=True, help="Print nothing but errors.")
@click.option("--count", type=click.IntRange(min=1), default=None, help="Live: stop after this many packets.")
@click.option("--timeout", type=click.FloatRange(min=0.01), default=None, metavar="SECONDS",
              help="Live: stop after this long.")
@limits_options
def capture_command(pcap: str | None, iface: str | None, port: int, output: str, split_size: int | None,
                    split_duration: float | None, keep_secrets: bool, checksum_rule: str | None, quiet: bool,
                    force: bool, count: int | None, timeout: float | None, answer_timeout: float, max_frame: int,
                    max_image: int) -> None:
    """Record traffic to PORT from a capture file or a live interface.

    Each TCP connection is reassembled in both directions by sequence number
    (retransmissions and reordering handled; bytes missing from the capture are
    recorded as gap events, never filled in) and written in the same layout as
    'whiztap record'.
    """
    if (pcap is None) == (iface is None):
        fail("give exactly one of --pcap FILE or --iface NAME")
    rule = check_checksum_rule(checksum_rule)
    check_output_free(output, split_size is not None or split_duration is not None, force,
                      inputs=[pcap] if pcap is not None else [])
    from whiztap.sniffer.record.capture import CaptureError, CaptureSettings, capture_live, import_pcap

    settings = CaptureSettings(port, output, split_size, split_duration, keep_secrets, rule,
                               limits_from(answer_timeout, max_frame, max_image), overwrite=force)
    try:
        if pcap is not None:
            from whiztap.analyzer.cli.analyze import ByteProgress

            # a bar on a terminal for a large file; a missing one is import_pcap's to report
            with ByteProgress([Path(pcap)] if os.path.isfile(pcap) else [], not quiet, "importing") as bar:
                summary = import_pcap(pcap, settings, progress=bar.update)
        else:
            summary = capture_live(iface, settings, count=count, timeout=timeout,  # type: ignore[arg-type]
                                   announce=None if quiet else say)
    except CaptureError as e:
        fail(str(e))
    if not quiet:
        for line in summary_lines(summary, "captured"):
            say(line)
