"""``whiztap replay`` and ``whiztap stub``: a recording against a server, or in place of one.

Imports stay light at module level (``whiztap --help`` loads this module); the
engines load when a command runs.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.cli.errors import fail, warn
from whiztap.analyzer.cli.output import check_output, recording_output, say
from whiztap.analyzer.cli.params import assumed_channels, assumed_map_options, force_option
from whiztap.analyzer.cli.reading import one_recording
from whiztap.analyzer.protocol.text import plural
from whiztap.sniffer.cli.params import Address, FaultSpecParam
from whiztap.sniffer.cli.run import run, stop_signals

if TYPE_CHECKING:
    from whiztap.analyzer.analysis.exchanges import RecordedSessions
    from whiztap.analyzer.protocol.messages import ChannelConfig
    from whiztap.analyzer.recording.sets import RecordingSet
    from whiztap.sniffer.replay.events import Event, ReplayResult
    from whiztap.sniffer.replay.episodes import Episodes
    from whiztap.sniffer.replay.options import ReplayOptions
    from whiztap.sniffer.replay.stub import Stub

PACES = ["recorded", "lockstep", "max"]


def _find(path: str) -> RecordingSet:
    """The recording a path names (a split one's parts together), or a one-line error."""
    return one_recording((path,))


def _load(path: str, recording: RecordingSet | None = None, timeout: float = 5.0,
          assumed: tuple[ChannelConfig, ...] = ()) -> RecordedSessions:
    """The recording's exchanges (``recording``: what ``_find`` found for
    ``path``; ``timeout``: how long its client waited for an answer), or a
    one-line error (exit status 2)."""
    from whiztap.analyzer.analysis.exchanges import load_exchanges
    from whiztap.analyzer.recording.scan import RecordingError

    try:
        return load_exchanges(recording or _find(path), int(timeout * 1e9), assumed)
    except OSError as e:
        fail(f"{path}: cannot read ({e.strerror or e})")
    except (RecordingError, KeyError) as e:  # KeyError: a message without a field the format requires
        fail(str(e) if path in str(e) else f"{path}: not a readable recording ({e})")


def _echo(text: str) -> None:
    """Print lines that quote the recording and the server (``say``: control
    characters shown, never obeyed; a closed standard output ends the printing)."""
    for line in text.split("\n"):
        say(line)


def _password(text: str | None) -> bytes | None:
    return text.encode() if text is not None else None


# -- replay ---------------------------------------------------------------------------------


@click.command("replay")
@click.argument("path", metavar="RECORDING")
@click.option("--target", type=Address("127.0.0.1"), metavar="HOST:PORT",
              help="The server to replay against (not needed with --dry-run).")
@click.option("--password", envvar="WHIZTAP_PASSWORD", default=None,
              help="Winsock password (default: $WHIZTAP_PASSWORD, or each connection's recorded one if "
                   "it was kept); connections refused in the recording send a wrong one.")
@click.option("--conn", "conns", type=int, multiple=True, help="Only this recorded connection; repeatable.")
@click.option("--pace", type=click.Choice(PACES), default="recorded", show_default=True,
              help="recorded: the original gaps / --rate; lockstep: each request waits for its answer; "
                   "max: as fast as the server reads.")
@click.option("--rate", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="Speed factor for --pace recorded (2.0 = twice as fast).")
@click.option("--segments", type=click.Choice(["frames", "exact"]), default="frames", show_default=True,
              help="frames: one write per frame; exact: the recorded TCP reads, byte boundaries and all.")
@click.option("--compare", "mode", type=click.Choice(["exact", "structure", "none"]), default="structure",
              show_default=True, help="How answers must match the recorded ones.")
@click.option("--tolerance", "tolerances", multiple=True, metavar="FIELD=N",
              help="Allow a numeric field to differ by N (e.g. sensor_value=20); repeatable.")
@click.option("--ignore-field", "ignore_fields", multiple=True, metavar="FIELD",
              help="Do not compare this field; repeatable.")
@click.option("--ignore-kind", "ignore_kinds", multiple=True, metavar="KIND",
              help="Do not compare answers of this kind (response, config, image, handshake, unframed, "
                   "sensor, servo); repeatable.")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=2.0, show_default=True,
              metavar="SECONDS", help="How long to wait for each answer (and the handshake).")
@click.option("--connect-timeout", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True,
              metavar="SECONDS", help="How long to try to connect.")
@click.option("--loop", type=click.IntRange(min=1), default=1, show_default=True, help="Replay N times.")
@click.option("--start", "start_s", type=float, default=None, metavar="S",
              help="Only what the client sent from S seconds after the recording's start.")
@click.option("--end", "end_s", type=float, default=None, metavar="S", help="... until S seconds (exclusive).")
@click.option("--kind", "kinds", multiple=True, metavar="KIND",
              help="Only client items of this kind; repeatable (see docs/replay.md for the names).")
@click.option("--faults-from-recording", "from_recording", is_flag=True,
              help="Re-apply the faults the recording was made under (those given to 'whiztap record' and "
                   "those added while it ran), through a proxy in the middle, with its seed, and compare "
                   "the answers with what the recorded client received.  Default: no faults.  Holds, hand "
                   "edits, injections and scripts are not re-applied.")
@click.option("--fault", "faults", type=FaultSpecParam(), multiple=True,
              help="A fault to apply through a proxy in the middle, as 'whiztap record --fault' takes it "
                   "(e.g. 'drop dir:s2c kind:response every:2'); repeatable, and after the recording's "
                   "with --faults-from-recording.")
@click.option("--seed", type=int, default=None,
              help="Seed for the faults' prob:, jitter: and slice ranges (default: the recording's, with "
                   "--faults-from-recording).")
@click.option("--dry-run", is_flag=True, help="Print what would be sent, and send nothing.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Write the replayed session as a recording.")
@force_option
@click.option("-v", "--verbose", is_flag=True, help="Print every write and every answer, not only differences.")
@click.option("-q", "--quiet", is_flag=True, help="Print only the summary.")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True,
              help="json: one object at the end (counts, differences, drift), for scripts.")
@assumed_map_options
def replay_command(path: str, target: tuple[str, int] | None, password: str | None, conns: tuple[int, ...], pace: str,
                   rate: float, segments: str, mode: str, tolerances: tuple[str, ...], ignore_fields: tuple[str, ...],
                   ignore_kinds: tuple[str, ...], timeout: float, connect_timeout: float, loop: int,
                   start_s: float | None, end_s: float | None, kinds: tuple[str, ...], from_recording: bool,
                   faults: tuple, seed: int | None, dry_run: bool, output: str | None, force: bool, verbose: bool,
                   quiet: bool, fmt: str, channel_map: str | None, assume_config: str | None) -> None:
    """Replay a recording's client side against a server and compare its answers.

    Exit status 0 when every answer matched, 1 on any difference, 2 when the
    file cannot be read or the target cannot be reached.  With
    --faults-from-recording, answers are compared with what the recorded
    client received, so a replay that reproduces it exits 0; the target's own
    answers, before the faults, are compared with the recorded server's and
    reported apart.
    """
    from whiztap.analyzer.analysis.compare import CompareError, CompareRules
    from whiztap.sniffer.replay.options import Pace, ReplayError, ReplayOptions
    from whiztap.sniffer.replay.plan import KINDS, Selection, dry_run_lines, plan

    recording_output(output)  # before anything is read: '-' is no place for a recording
    unknown = [k for k in kinds if k not in KINDS]
    if unknown:
        fail(f"--kind: unknown kind {unknown[0]!r}; kinds are {', '.join(KINDS)}")
    if start_s is not None and end_s is not None and end_s <= start_s:
        fail("--end must be after --start")
    if seed is not None and not (faults or from_recording):
        fail("--seed seeds faults: give --fault or --faults-from-recording")
    try:
        rules = CompareRules.parse(mode, tolerances, ignore_fields, ignore_kinds)
    except CompareError as e:
        fail(str(e))
    selection = Selection(frozenset(conns), start_s, end_s, frozenset(kinds))
    found = _find(path)
    check_output(output, found.parts, force=force, recording=True)
    assumed = assumed_channels(channel_map, assume_config)
    recording = _load(path, found, timeout, assumed)
    faults, seed = _faults(found, recording.metadata, faults, from_recording, seed)
    if dry_run:
        plans = plan(recording, selection, segments == "exact")
        if not plans:
            fail("nothing to replay: no connection is selected")
        for line in _fault_lines(faults, seed) + dry_run_lines(plans, recording.start_ns):
            _echo(line)
        return
    if target is None:
        fail("--target HOST:PORT is required (or --dry-run)")
    options = ReplayOptions(target=target, password=_password(password), pace=Pace(pace),
                            rate=rate, segments=segments == "exact", rules=rules, timeout=timeout,
                            connect_timeout=connect_timeout, loop=loop, selection=selection, output=output,
                            checksum_rule=recording.checksum_rule, faults=faults, fault_seed=seed,
                            reproduce=from_recording, assumed_channels=assumed)
    try:
        result = run(_replay(recording, options, verbose, quiet, fmt == "json"))
    except ReplayError as e:
        fail(e.explained({"password": "give --password or set WHIZTAP_PASSWORD"}))  # --target is checked above
    if result.error:
        fail(result.error)
    if result.stopped:
        fail("interrupted")
    sys.exit(result.exit_status)


def _faults(found: RecordingSet, metadata: dict[str, str], typed: tuple, from_recording: bool,
            seed: int | None) -> tuple[tuple, int | None]:
    """The faults to replay under, and their seed: none by default; with
    --faults-from-recording the recording's (a note when it has none), then
    those typed in with --fault."""
    if not from_recording:
        return tuple(typed), seed
    from whiztap.sniffer.replay.faults import recorded_faults
    from whiztap.sniffer.replay.options import ReplayError

    try:
        recorded = recorded_faults([p for p in found.parts if isinstance(p, Path)], metadata)  # files, not URLs
    except ReplayError as e:
        fail(str(e))
    if not recorded.faults:
        warn(f"note: {found} was recorded without faults: there are none to re-apply")
    return recorded.faults + tuple(typed), recorded.seed if seed is None else seed


def _fault_lines(faults: tuple, seed: int | None) -> list[str]:
    """The faults a replay goes through, one line each, for people."""
    from whiztap.sniffer.replay.faults import fault_text

    if not faults:
        return []
    return [f"through a proxy in the middle (seed {'none' if seed is None else seed}):"] + \
        [f"  {fault_text(f)}" for f in faults]


async def _replay(recording: RecordedSessions, options: ReplayOptions, verbose: bool, quiet: bool,
                  as_json: bool) -> ReplayResult:
    from whiztap.sniffer.replay.engine import Replay

    printer = _Printer(verbose, quiet or as_json)
    replay = Replay(recording, options, on_event=printer)
    replay.check()
    if not (quiet or as_json):
        host, port = options.address
        target = f"{host}:{port}"
        _echo(f"replaying {recording.path} against {target}: {plural(len(replay.plans), 'connection')}, "
                   f"pace {options.pace}" + (f" x{options.rate:g}" if options.pace == "recorded" else "")
                   + f", {options.rules.describe()}")
        for line in _fault_lines(options.faults, options.fault_seed):
            _echo(line)
    with stop_signals(replay.stop):
        result = await replay.run()
    if result.error:
        return result
    if as_json:
        import json

        host, port = options.address
        target = f"{host}:{port}"
        click.echo(json.dumps({"recording": recording.path, "target": target, "pace": str(options.pace),
                               "rate": options.rate, "compare": {
                                   "mode": str(options.rules.mode), "tolerances": dict(options.rules.tolerances),
                                   "ignore_fields": sorted(options.rules.ignore_fields),
                                   "ignore_kinds": sorted(options.rules.ignore_kinds)},
                               "faults": [{"name": f.name, "spec": f.text} for f in options.faults],
                               "fault_seed": options.fault_seed, "output": options.output, **result.as_dict()},
                              indent=2))
        return result
    _echo(result.summary())
    if result.server is not None:
        _echo(result.server.summary())
        for difference in result.server.differences:
            _echo("  " + difference.diff.replace("\n", "\n  "))
    if result.drift is not None:
        _echo(result.drift.text())
    elif options.pace != "recorded":
        _echo(f"drift: none measured (pace {options.pace} keeps no schedule)")
    if options.output:
        _echo(f"wrote {options.output}")
    if not result.stopped:  # stopped: 'interrupted' (exit status 2) is the one status, said by the command
        _echo("result: " + ("all answers matched" if result.ok else "DIFFERENCES (exit status 1)"))
    return result


class _Printer:
    """Prints events as they come: differences always, the rest with -v."""

    def __init__(self, verbose: bool, quiet: bool) -> None:
        self.verbose, self.quiet = verbose, quiet

    def __call__(self, event: Event) -> None:
        from whiztap.analyzer.protocol.text import escape, shorten
        from whiztap.sniffer.replay.events import ConnectionClosed, ConnectionOpened, RequestSent, ResponseCompared

        if self.quiet:
            return
        if isinstance(event, ResponseCompared):
            if not event.match:
                _echo(event.diff)
            elif self.verbose:
                shown = shorten(escape(event.replayed), 72) if event.replayed is not None else "(no answer)"
                _echo(f"{event.at_s:10.6f} c{event.conn} < {shown}  {event.status}")
        elif not self.verbose:
            return
        elif isinstance(event, RequestSent):
            drift = f"  (+{event.drift_ns / 1e6:.3f} ms)" if event.drift_ns is not None else ""
            _echo(f"{event.at_s:10.6f} c{event.conn} > {shorten(escape(event.data), 72)}  {event.text}{drift}")
        elif isinstance(event, ConnectionOpened):
            _echo(f"{event.at_s:10.6f} c{event.conn} opened from {event.local} "
                       f"(recorded connection {event.recorded_conn}, loop {event.loop})")
        elif isinstance(event, ConnectionClosed):
            _echo(f"{event.at_s:10.6f} c{event.conn} closed by {event.by}")


# -- stub -------------------------------------------------------------------------------------


@click.command("stub")
@click.argument("path", metavar="RECORDING")
@click.option("--listen", type=Address("127.0.0.1"), default="127.0.0.1:5000", show_default=True, metavar="[HOST:]PORT",
              help="Where clients connect (port 0 picks a free one, printed).")
@click.option("--password", default=None, help="Check the winsock password (default: accept any).")
@click.option("--conn", type=int, default=None, help="Answer every client from this recorded connection.")
@click.option("--pace", type=click.Choice(["recorded", "max"]), default="max", show_default=True,
              help="recorded: answer after the recorded delay (/ --rate); max: at once.")
@click.option("--rate", type=click.FloatRange(min=0, min_open=True), default=1.0, show_default=True,
              help="Speed factor for --pace recorded.")
@click.option("--when-exhausted", "exhausted", type=click.Choice(["repeat", "fail"]), default="repeat",
              show_default=True, help="When a kind's recorded answers are used up: repeat the last, or answer "
                                      "nothing (and count the request as unanswered).")
@click.option("--unmatched", default="close", show_default=True, metavar="close|ignore|FRAME",
              help="A request with no recorded answer: close the client's connection, ignore it (send nothing), "
                   "or send FRAME (escaped text, e.g. 'cr1-0--0--0-ss1').")
@click.option("--match", "match_text", default="kind,channel,order", show_default=True,
              metavar="kind,channel,value,order",
              help="The fields a request must share with a recorded one to get its answer: kind (required), "
                   "channel, value (the whole frame, byte for byte), order (the k-th such request gets the "
                   "k-th answer; without it, always the first).")
@click.option("--strict", is_flag=True, help="Exit with status 1 if any request had no recorded answer.")
@click.option("--fail-unused", is_flag=True, help="Exit with status 1 if a recorded request was never asked for.")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True,
              help="json: the closing summary as one JSON object (misses with their closest recorded "
                   "requests, unused recorded requests), for scripts.")
@click.option("--upstream", type=Address("127.0.0.1"), default=None, metavar="HOST:PORT",
              help="The real server: a request the recording has no answer for is forwarded to it, on one "
                   "upstream connection per client (logged in with the client's own password), and the new "
                   "exchanges are appended to RECORDING when the stub stops, all at once (nothing on a failure).")
@click.option("--upstream-timeout", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True,
              metavar="SECONDS", help="How long to wait for the upstream's connection, handshake and each answer.")
@click.option("--once", is_flag=True, help="Exit after the first client disconnects.")
@click.option("-q", "--quiet", is_flag=True, help="Print only the listening line and problems.")
@assumed_map_options
def stub_command(path: str, listen: tuple[str, int], password: str | None, conn: int | None, pace: str, rate: float,
                 exhausted: str, unmatched: str, match_text: str, strict: bool, fail_unused: bool, fmt: str,
                 upstream: tuple[str, int] | None, upstream_timeout: float,
                 once: bool, quiet: bool, channel_map: str | None, assume_config: str | None) -> None:
    """Serve a recording's server side to a client under test.

    Each client is answered from one recorded connection: by default the k-th
    client from the k-th recorded connection that completed its handshake (VPN,
    or a Winsock login the server let in; later clients from the last such);
    --conn N answers every client from connection N, a refused login included.
    Each request gets the recorded answer to the same kind of request on the
    same channel, in recorded order; one it cannot answer is met as --unmatched
    says, with the closest recorded requests and what differs.  At the end the
    recorded requests no client asked for are listed.  Runs until Ctrl-C or
    SIGTERM (or, with --once, until the first client leaves).  With
    --upstream, misses are asked of the real server instead and appended to
    RECORDING at the end (exit status 2, RECORDING unchanged, if it failed).
    """
    from whiztap.sniffer.replay.near_miss import Match
    from whiztap.sniffer.replay.stub import Stub

    try:
        match = Match.parse(match_text)
    except ValueError as e:
        fail(str(e))

    assumed = assumed_channels(channel_map, assume_config)
    found = _find(path)
    recording = _load(path, found, assumed=assumed)
    episodes = _episodes(found, recording, upstream, upstream_timeout)

    def log(line: str) -> None:
        if not quiet or line.startswith("!"):
            _echo(line)

    reaction: str | bytes = unmatched
    if unmatched not in ("close", "ignore"):
        from whiztap.analyzer.protocol.text import unescape

        reaction = unescape(unmatched)
    try:
        stub = Stub(recording, *listen, password=_password(password), pace=pace, rate=rate,
                    exhausted=exhausted, conn=conn, unmatched=reaction, match=match, on_log=log,
                    assumed_channels=assumed, episodes=episodes)
    except ValueError as e:
        fail(str(e))
    _begin(episodes)
    error = run(_serve(stub, once))
    appended = _append(episodes)
    if error:
        fail(error)
    missing, unused = len(stub.unanswered), stub.unused()
    _summary(stub, match.text(), appended, fmt == "json", quiet, fail_unused)
    if episodes is not None and episodes.failure is not None:
        fail(f"upstream {episodes.upstream_text}: {episodes.failure}; nothing appended, {stub.recording.path} "
             "is unchanged: run again once the server answers")
    sys.exit(1 if (strict and missing) or (fail_unused and unused) else 0)


def _summary(stub: Stub, match: str, appended: bool, as_json: bool, quiet: bool, fail_unused: bool) -> None:
    """The stub's closing summary: one JSON object, or text lines."""
    episodes = stub.episodes
    missing, unused = len(stub.unanswered), stub.unused()
    if as_json:
        import json

        more = {} if episodes is None else {"upstream": episodes.upstream_text, "forwarded": stub.forwarded,
                                            "appended": appended, "upstream_error": episodes.failure}
        _echo(json.dumps({"recording": stub.recording.path, "match": match, "connections": stub.connections,
                          "answers": stub.answers, "unanswered": [u.as_dict() for u in stub.unanswered],
                          "unused": [r.as_dict() for r in unused], **more}))
    else:
        _echo(f"served {plural(stub.connections, 'connection')}, {plural(stub.answers, 'answer')}; "
              f"{plural(missing, 'request')} without a recorded answer"
              + (f"; {plural(len(unused), 'recorded request')} never asked for" if unused else ""))
        if unused and (fail_unused or not quiet):
            for r in unused:
                _echo(f"  unused: #{r.conn} request {r.position} {r.text}")
        if episodes is not None and episodes.failure is None:
            _echo(f"{plural(stub.forwarded, 'request')} forwarded to {episodes.upstream_text}; "
                  + (f"appended to {stub.recording.path} on {plural(episodes.connections, 'new connection')}"
                     if appended
                     else f"nothing new: {stub.recording.path} unchanged"))


def _episodes(found: RecordingSet, recording: RecordedSessions, upstream: tuple[str, int] | None,
              timeout: float) -> Episodes | None:
    """What records the new episodes for --upstream, or a one-line error."""
    if upstream is None:
        return None
    from whiztap.sniffer.replay.episodes import Episodes

    if len(found.parts) != 1 or not isinstance(found.name, Path):
        fail(f"--upstream appends to RECORDING, so it must be one local file, not {found}: make one with "
             "'whiztap cut PARTS... -o ONE.mcap'")
    return Episodes(found.name, upstream, recording.checksum_rule, timeout)


def _begin(episodes: Episodes | None) -> None:
    """Begin recording new episodes, or a one-line error."""
    if episodes is None:
        return
    from whiztap.sniffer.record.writer import RecordingWriteError

    try:
        episodes.open()
    except (OSError, RecordingWriteError) as e:
        fail(f"--upstream: cannot record new episodes ({getattr(e, 'strerror', None) or e})")


def _append(episodes: Episodes | None) -> bool:
    """Append the new episodes, if any (a failed append leaves RECORDING as it was)."""
    if episodes is None:
        return False
    from whiztap.analyzer.recording.scan import RecordingError
    from whiztap.sniffer.record.writer import RecordingWriteError

    try:
        return episodes.finish()
    except (OSError, RecordingError, RecordingWriteError) as e:
        fail(f"cannot append the new episodes to {episodes.path} ({getattr(e, 'strerror', None) or e}); "
             "it is unchanged")


async def _serve(stub: Stub, once: bool) -> str | None:
    try:
        await stub.start()
    except OSError as e:
        return f"cannot listen on {stub.host}:{stub.requested_port}: {e.strerror or e}"
    where = ", ".join(f"{h}:{p}" for h, p in stub.addresses)
    _echo(f"whiztap stub: serving {stub.recording.path} on {where} "
               f"({plural(len(stub.recording.connections), 'recorded connection')})")
    import asyncio

    stopped = asyncio.Event()
    waiters = [asyncio.create_task(stopped.wait())]
    if once:
        waiters.append(asyncio.create_task(stub.finished.wait()))
    try:
        with stop_signals(stopped.set):
            await asyncio.wait(waiters, return_when=asyncio.FIRST_COMPLETED)
    finally:
        for task in waiters:
            task.cancel()
        await stub.close()
    return None
