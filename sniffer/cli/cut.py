"""``whiztap cut``: a recording cut down to the connections that matter, as a
recording every reader opens (docs/cut.md)."""

from __future__ import annotations

import sys

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output, say
from whiztap.analyzer.cli.params import checksum_rule_option, force_option, limits_from, limits_options
from whiztap.analyzer.protocol.text import plural


def _conn_list(values: tuple[str, ...]) -> frozenset[int]:
    """``--conn 1,3 --conn 4`` as {1, 3, 4}."""
    try:
        return frozenset(int(v) for value in values for v in value.split(",") if v.strip())
    except ValueError:
        fail(f"--conn: wants connection numbers separated by commas (1,3), got {' '.join(values)!r}")


@click.command("cut")
@click.argument("inputs", nargs=-1, required=True, metavar="RECORDING")
@click.option("-o", "--output", required=True, type=click.Path(dir_okay=False, allow_dash=True),
              help="The new recording (a file: a recording is never written to standard output).")
@force_option
@click.option("--filter", "filter_text", default="", metavar="WORDS",
              help="Keep the connections with an item that matches these words, as cat --filter and the TUI's "
                   "filter bar take them (\"kind:response ch:12 violations\").")
@click.option("--start", default=None, metavar="T",
              help="Only items from T on: seconds after the first traffic (2.5, 2.5s, 250ms) or an ISO time.")
@click.option("--end", default=None, metavar="T", help="Only items before T (same forms as --start).")
@click.option("--conn", "conns", multiple=True, metavar="N,...", help="Only these connections; repeatable.")
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@limits_options
def cut_command(inputs: tuple[str, ...], output: str, force: bool, filter_text: str, start: str | None,
                end: str | None, conns: tuple[str, ...], checksum_rule: str, answer_timeout: float,
                max_frame: int, max_image: int) -> None:
    """Write a new recording holding only the connections that match.

    A connection is kept whole, from its opening to its close (handshake,
    password, configuration and all), when it is one of --conn and one of its
    items matches --filter between --start and --end: so `analyze` of the cut
    gives each kept connection the verdict it had in RECORDING.  Exit status 1
    when nothing matches (no file is written).
    """
    from whiztap.analyzer.analysis.item_filter import FilterSyntaxError, parse_filter
    from whiztap.analyzer.cli.progress import ByteProgress
    from whiztap.analyzer.cli.reading import one_recording, scan_recording
    from whiztap.analyzer.recording.scan import RecordingError
    from whiztap.sniffer.record.cut import chosen_connections, copy_connections, parse_bound
    from whiztap.sniffer.record.writer import RecordingWriteError

    try:
        item_filter = parse_filter(filter_text)
    except FilterSyntaxError as e:
        fail(f"--filter: {e}")
    wanted = _conn_list(conns)
    if wanted:
        from dataclasses import replace

        item_filter = replace(item_filter, conns=wanted & item_filter.conns if item_filter.conns else wanted)
    bounds = []  # --start and --end, or else the filter's since: and until:
    for option, text, word in (("--start", start, item_filter.since_s), ("--end", end, item_filter.until_s)):
        given = text if text is not None else None if word is None else str(word)
        try:
            bounds.append(parse_bound(given) if given is not None else None)
        except ValueError as e:
            fail(f"{option if text is not None else '--filter'}: {e}")
    recording = one_recording(inputs)
    parts = list(recording.parts)
    check_output(output, parts, force=force, recording=True)
    limits = limits_from(answer_timeout, max_frame, max_image)
    with ByteProgress(parts, enabled=True, doing="choosing") as progress:
        kept = chosen_connections(scan_recording(recording, progress), item_filter, bounds[0], bounds[1],
                                  str(recording.name), checksum_rule, limits)
    if not kept:
        click.echo(f"nothing in {recording} matches: {output} not written", err=True)
        sys.exit(1)
    try:
        with ByteProgress(parts, enabled=True, doing="cutting") as progress:
            written = copy_connections(parts, output, kept, force=force, open_file=progress.open)
    except (RecordingError, RecordingWriteError) as e:
        fail(str(e))
    except OSError as e:
        fail(f"cannot cut {recording}: {e.strerror or e}")
    numbers = sorted(kept)
    shown = ",".join(map(str, numbers[:10])) + (f" and {len(numbers) - 10} more" if len(numbers) > 10 else "")
    say(f"{output}: {plural(len(kept), 'connection')} ({shown}), {plural(written, 'message')}")
