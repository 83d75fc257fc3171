"""``whiztap info``: file-level facts about a recording."""

from __future__ import annotations

import shlex
from pathlib import Path

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.reading import one_recording


@click.command("info")
@click.argument("inputs", nargs=-1, required=True, metavar="RECORDING")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True)
def info_command(inputs: tuple[str, ...], fmt: str) -> None:
    """File-level facts: format version, session metadata, time span,
    connections, messages per topic, size, and whether the file is complete;
    for a recording made with the proxy in the middle, that it was and how
    many interventions it holds.  A split recording (its first part, folder or
    a glob) is shown as one, with its parts listed."""
    from whiztap.analyzer.recording.info import set_info
    from whiztap.analyzer.protocol.text import plural, printable

    recording = one_recording(inputs)
    path_ = recording.parts[-1]
    try:
        info = set_info([p for p in recording.parts if isinstance(p, Path)])  # files: one_recording takes no URL
    except OSError as e:
        fail(f"{path_}: cannot read ({e.strerror})")
    except ValueError as e:
        fail(f"{path_}: {e}")
    from whiztap.analyzer.recording.format import TOPIC_INTERVENTIONS

    interventions = info["topics"].get(TOPIC_INTERVENTIONS, 0)
    middle = info["metadata"].get("middle") == "yes" or interventions > 0
    if middle:  # only then: the facts of any other recording stay as they were
        info["middle"] = True
        info["interventions"] = interventions
    if fmt == "json":
        import json

        click.echo(json.dumps(info, indent=2))
        return
    # names and metadata come from the file: a terminal must show them, never obey them
    click.echo(f"file            {printable(info['path'])}")
    for part in info.get("parts", []):
        click.echo(f"  part          {printable(part['path'])} ({plural(part['size_bytes'], 'byte')}, "
                   f"{printable(part['state'])})")
    click.echo(f"size            {plural(info['size_bytes'], 'byte')}")
    click.echo(f"complete        {'yes (indexed)' if info['complete'] else 'NO: ' + printable(info['state'])}")
    version = info["format_version"]
    click.echo(f"format version  {printable(version) if version else 'unknown (not written by whiztap?)'}")
    for key, value in info["metadata"].items():
        click.echo(f"  {printable(key):14} {printable(value)}")
    click.echo(f"time span       {info['start']} .. {info['end']} ({info['duration_s']:.3f} s)")
    click.echo(f"connections     {info['connections']}")
    if middle:
        click.echo(f"in the middle   yes: the proxy changed the traffic {plural(interventions, 'time')} "
                   "(whiztap cat --interventions only lists them)")
    click.echo("messages per topic")
    width = max((len(topic) for topic in info["topics"]), default=0)  # /mirror/differences is 19
    for topic, n in info["topics"].items():
        click.echo(f"  {topic:{max(width, 16)}} {n:,}")
    if not info["complete"] and not info["state"].startswith("being written"):
        click.echo(printable(f"To make a complete, indexed copy: whiztap recover {shlex.quote(str(path_))}"))
