"""``whiztap record``, ``whiztap recover`` and ``whiztap capture``.

Heavy imports (asyncio machinery, uvloop, mcap, scapy) stay inside the command
functions so that ``whiztap --help`` does not pay for them.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import click

from whiztap.analyzer.cli.errors import fail, warn
from whiztap.analyzer.cli.output import recording_output, say
from whiztap.analyzer.cli.params import assumed_map_options, force_option, limits_assuming, limits_from, limits_options
from whiztap.analyzer.protocol.text import printable
from whiztap.sniffer.cli.params import (
    Address,
    check_recording_output,
    foxglove_option,
    middle_options,
    middle_settings,
    recording_options,
)
from whiztap.sniffer.cli.run import run, stop_signals
from whiztap.sniffer.record.summary import fault_lines, summary_lines

if TYPE_CHECKING:
    from whiztap.sniffer.record.record_run import RecordSettings, Recording


class _Checked(click.ParamType):
    """A --ring, --trigger or --after value read by its parser (sniffer/record/trigger.py);
    one line when it is not one."""

    def __init__(self, name: str) -> None:
        self.name = name

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value
        from whiztap.sniffer.record.trigger import parse_duration, parse_ring, parse_trigger

        parse = {"ring": parse_ring, "trigger": parse_trigger, "after": parse_duration}[self.name]
        try:
            return parse(value)
        except ValueError as e:
            fail(f"--{self.name} {e}")


def _ring_settings(output: str, ring: Any, triggers: tuple[str, ...], after: float | None, split: bool,
                   foxglove: bool) -> Any:
    """--ring's settings (None without it), checked together: one line for what does not go."""
    if ring is None:
        if triggers or after is not None:
            fail("--trigger and --after go with --ring DURATION|SIZE (the flight recorder)")
        return None
    if not triggers:
        fail("--ring needs at least one --trigger RULE|severity:LEVEL|latency>MS|fault: what begins an incident")
    if split or foxglove:
        fail("--ring writes incident files only: it does not go with --split-size, --split-duration or --foxglove")
    from whiztap.sniffer.record.ring import incident_path
    from whiztap.sniffer.record.trigger import DEFAULT_AFTER_S, RingSettings

    check_recording_output(incident_path(output, 1), False, True)  # the folder; a name taken is skipped
    slowest = max((float(w.partition(">")[2]) for w in triggers if w.startswith("latency>")), default=0.0)
    if ring.duration_ns is not None and slowest * 1e6 >= ring.duration_ns:
        warn(f"warning: --ring {ring.describe()} is not longer than latency>{slowest:g}: a request never "
             f"answered is out of the window when its incident begins")
    return RingSettings(ring, tuple(dict.fromkeys(triggers)), DEFAULT_AFTER_S if after is None else after)


@click.command("record")
@click.option("--listen", type=Address("127.0.0.1"), default="127.0.0.1:6000", show_default=True,
              metavar="[HOST:]PORT", help="Where clients connect (port 0 picks a free one).")
@click.option("--upstream", type=Address(), required=True, metavar="HOST:PORT", help="The real server.")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The .mcap file to write.")
@recording_options
@click.option("-q", "--quiet", is_flag=True,
              help="Print only the first line (it names the listening address) and errors.")
@click.option("--analyze", is_flag=True, help="Print each violation as it happens.")
@click.option("--connect-timeout", type=click.FloatRange(min=0.01), default=5.0, show_default=True,
              metavar="SECONDS", help="How long to try the upstream for each client.")
@click.option("--when-behind", type=click.Choice(["pause", "gap"]), default="pause", show_default=True,
              help="When the recording falls behind the traffic, the connections causing it: pause them "
                   "(the recording stays complete), or keep them flowing and record a gap event "
                   "with the count of bytes left out.")
@click.option("--meta", "meta", multiple=True, metavar="KEY=VALUE",
              help="Write this key into the recording's metadata (robot=r7, firmware=2.3), for "
                   "'whiztap analyze --group-by KEY'; repeatable.")
@click.option("--ring", type=_Checked("ring"), default=None, metavar="DURATION|SIZE",
              help="Flight recorder: keep only this much (30s, 64MB) and write NAME-incident-N.mcap around each "
                   "--trigger (docs/recorder.md).")
@click.option("--trigger", "triggers", type=_Checked("trigger"), multiple=True,
              metavar="RULE|severity:LEVEL|latency>MS|fault",
              help="With --ring, what begins an incident: a rule id, a violation at or above LEVEL, an answer "
                   "slower than MS ms (or none within it), any fault of the proxy in the middle; repeatable.")
@click.option("--after", type=_Checked("after"), default=None, metavar="DURATION",
              help="With --ring, how long an incident goes on after its last trigger (default 5s).")
@click.option("--mirror", type=Address(), default=None, metavar="HOST:PORT",
              help="Shadow traffic: also send each client's bytes to this server, record its answers (never "
                   "sent to the client) and what differs from the primary's (docs/recorder.md).")
@foxglove_option
@middle_options
@limits_options
@assumed_map_options
def record_command(listen: tuple[str, int], upstream: tuple[str, int], output: str, split_size: int | None,
                   split_duration: float | None, keep_secrets: bool, checksum_rule: str, quiet: bool, force: bool,
                   analyze: bool, connect_timeout: float, when_behind: str, meta: tuple[str, ...],
                   foxglove: tuple[str, int] | None, answer_timeout: float, max_frame: int, max_image: int,
                   channel_map: str | None, assume_config: str | None, ring: Any, triggers: tuple[str, ...],
                   after: float | None, mirror: tuple[str, int] | None, **middle: Any) -> None:
    """Proxy clients to the server and record every byte into an MCAP file.

    Point the client at --listen instead of the robot: every byte is forwarded
    unchanged in both directions and recorded with its receive time.  Ctrl-C or
    SIGTERM closes the connections and finishes the file.  With --foxglove the
    Foxglove app can watch it live (Open connection, Foxglove WebSocket,
    ws://127.0.0.1:8765).

    With --fault, --faults, --control or --script the proxy stands in the
    middle: it delays, drops, corrupts, holds, edits or injects frames as
    asked, records every change on /interventions and what each side
    received on /tcp/delivered (docs/faults.md).
    """
    from whiztap.sniffer.record.metadata import MetadataError, user_metadata

    try:
        keys = user_metadata(meta)
    except MetadataError as e:
        fail(str(e))
    if mirror is not None and mirror == listen and listen[1] != 0:
        fail(f"--mirror {':'.join(map(str, mirror))} is where the proxy listens: each connection would open "
             "another through itself; name the second server")
    split = split_size is not None or split_duration is not None
    flight = _ring_settings(output, ring, triggers, after, split, foxglove is not None)
    if flight is None:
        check_recording_output(output, split, force)
    from whiztap.sniffer.record.record_run import RecordSettings

    settings = RecordSettings(listen, upstream, output, split_size, split_duration, keep_secrets, checksum_rule,
                              quiet, analyze, connect_timeout,
                              limits_assuming(limits_from(answer_timeout, max_frame, max_image), channel_map,
                                              assume_config),
                              overwrite=force, when_behind=when_behind, foxglove=foxglove,
                              middle=middle_settings(**middle), meta=tuple(keys.items()), ring=flight,
                              mirror=mirror)
    error = run(_record(settings))
    if error:
        fail(error)


async def _record(settings: RecordSettings) -> str | None:
    """Record until Ctrl-C, SIGTERM, SIGHUP or a write error; the error, if any."""
    import asyncio

    from whiztap.sniffer.nettext import show_address
    from whiztap.sniffer.record.feed import WriterError
    from whiztap.sniffer.record.record_run import Recording, StartError
    from whiztap.sniffer.record.ring import incident_path

    from whiztap.analyzer.mitm.spec import FaultSpecError
    from whiztap.sniffer.mitm.scripts import ScriptError

    echo = (lambda line: None) if settings.quiet else say
    recording = Recording(settings, echo)
    try:
        await recording.start()
    except (WriterError, FaultSpecError, ScriptError, StartError) as e:
        return str(e)
    except OSError as e:
        return f"cannot listen on {show_address(*settings.listen)}: {e.strerror or e}"
    proxy = recording.proxy
    assert proxy is not None  # started
    if not settings.quiet and recording.controller is not None:  # each fault in words, before any traffic
        for line in fault_lines(recording.controller.faults):
            click.echo(printable(line), err=True)
    with stop_signals(recording.stopped.set):
        # even with -q: with port 0 this line is the only way to learn the port
        live = f", foxglove: {recording.foxglove_url}" if recording.foxglove_url else ""
        live += f", control: {recording.control_text}" if recording.control_text else ""
        live += f", mirror: {recording.mirror.text}" if recording.mirror is not None else ""
        into = settings.output if settings.ring is None else \
            f"a {settings.ring.ring.describe()} ring, incidents into {incident_path(settings.output, 'N')}"
        say(f"recording {proxy.listen_text} -> {proxy.upstream_text} into {into}{live} (Ctrl-C to stop)")
        probe = asyncio.ensure_future(_try_upstream(recording))
        await recording.stopped.wait()
        probe.cancel()
        summary = await recording.stop("write error" if recording.error else "recording stopped")
    if summary is not None:
        for line in summary_lines(summary, "recorded"):
            echo(line)
        if summary.get("mirror"):
            from whiztap.sniffer.record.mirror import mirror_lines

            for line in mirror_lines(summary["mirror"]):
                echo(printable(line))
    return recording.error


async def _try_upstream(recording: Recording) -> None:
    """Connect to the upstream (and the mirror) once at start (and close at once): one that
    refuses is said now, rather than by each client's reset (the mirror's: by its first failure)."""
    from whiztap.sniffer.nettext import show_address
    from whiztap.sniffer.record.proxy import try_upstream

    settings = recording.settings
    why = await try_upstream(*settings.upstream, settings.connect_timeout)
    if why is not None:
        recording.warn(f"warning: the upstream {show_address(*settings.upstream)} does not accept connections ({why}); "
                       "recording anyway: each client is reset until it does")
    mirror = recording.mirror
    why = await try_upstream(mirror.host, mirror.port, settings.connect_timeout) if mirror is not None else None
    if mirror is not None and why is not None:  # said once: the first client's failure is not said again
        mirror.say_once("failed", f"warning: the mirror {mirror.text} does not accept connections ({why}); recording "
                                  "anyway: the clients' traffic goes on, and the mirror's answers are not compared")


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
@click.option("--port", type=click.IntRange(1, 65535), default=None,
              help="The server's TCP port (default: find Progwhiz conversations on any port by their content).")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False), help="The .mcap file to write.")
@recording_options
@click.option("-q", "--quiet", is_flag=True, help="Print nothing but errors.")
@click.option("--count", type=click.IntRange(min=1), default=None, help="Live: stop after this many packets.")
@click.option("--timeout", type=click.FloatRange(min=0.01), default=None, metavar="SECONDS",
              help="Live: stop after this long.")
@limits_options
def capture_command(pcap: str | None, iface: str | None, port: int | None, output: str, split_size: int | None,
                    split_duration: float | None, keep_secrets: bool, checksum_rule: str, quiet: bool,
                    force: bool, count: int | None, timeout: float | None, answer_timeout: float, max_frame: int,
                    max_image: int) -> None:
    """Record traffic to PORT from a capture file or a live interface.

    Each TCP connection is reassembled in both directions by sequence number
    (retransmissions and reordering handled; bytes missing from the capture are
    recorded as gap events, never filled in) and written in the same layout as
    'whiztap record'.

    Without --port, every TCP conversation whose first bytes are Progwhiz (a
    frame header such as rr1- or cr1-, or a handshake word such as
    sendchkpass) is recorded, whatever its port; the side that sent them tells
    which is the server (docs/wireshark.md).
    """
    if (pcap is None) == (iface is None):
        fail("give exactly one of --pcap FILE or --iface NAME")
    check_recording_output(output, split_size is not None or split_duration is not None, force,
                           inputs=(pcap,) if pcap is not None else ())
    from whiztap.sniffer.record.capture import CaptureError, CaptureSettings, capture_live, import_pcap

    settings = CaptureSettings(port, output, split_size, split_duration, keep_secrets, checksum_rule,
                               limits_from(answer_timeout, max_frame, max_image), overwrite=force)
    try:
        if pcap is not None:
            from whiztap.analyzer.cli.progress import ByteProgress

            # a bar on a terminal for a large file; a missing one is import_pcap's to report
            with ByteProgress([Path(pcap)] if os.path.isfile(pcap) else [], not quiet, "importing") as bar:
                summary = import_pcap(pcap, settings, progress=bar.update)
        else:
            assert iface is not None  # one of the two, as checked above
            summary = capture_live(iface, settings, count=count, timeout=timeout,
                                   announce=None if quiet else say)
    except CaptureError as e:
        fail(str(e))
    if not quiet:
        for line in summary_lines(summary, "captured"):
            say(line)
