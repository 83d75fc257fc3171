"""``whiztap tui`` and ``whiztap demo``.

Textual and the proxy are imported inside the commands, so that ``whiztap
--help`` does not pay for them.  Everything the user can get wrong (a missing
file, a bad address, a port in use) is one line and exit status 2.
"""

from __future__ import annotations

import sys
from typing import TYPE_CHECKING, Any

import click
from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output
from whiztap.analyzer.cli.params import (
    assumed_map_options, checksum_rule_option, force_option, limits_assuming, limits_from, limits_options)
from whiztap.analyzer.cli.reading import one_recording
from whiztap.sniffer.cli.params import (
    Address,
    check_recording_output,
    foxglove_option,
    middle_given,
    middle_options,
    middle_settings,
)

if TYPE_CHECKING:
    from whiztap.analyzer.recording.sets import RecordingSet
    from whiztap.sniffer.record.record_run import MiddleSettings
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.data.sources import LiveSource, Source

HEADLESS_SECONDS = 5.0  # `whiztap demo` without a terminal, as `make demo` in CI


def _check_recording(path: str) -> None:
    from whiztap.analyzer.recording.scan import RecordingError, read_metadata

    try:
        read_metadata(path)
    except RecordingError as e:
        fail(f"{path}: {e}")
    except OSError as e:
        fail(f"{path}: cannot read ({e.strerror})")


def _one_recording(path: str) -> RecordingSet:
    """The recording to browse: a file, or a split one named by any of its parts,
    its folder or a glob; checked readable before the app starts."""
    recording = one_recording((path,))
    for part in recording.parts:
        _check_recording(str(part))
    return recording


def _need_terminal(what: str) -> None:
    if not (sys.stdin.isatty() and sys.stdout.isatty()):
        fail(f"{what} needs a terminal; for a report use 'whiztap analyze', for frames 'whiztap cat'")


def _hints(path: str, password: str = "PASSWORD", seed: int | None = None) -> list[str]:
    """What to do with a recording just made (printed when the app ends), as
    commands a shell takes as they are (paths quoted).  ``seed``: the demo's
    robot's, so that the simulator the replay hint names answers as it did."""
    import shlex
    from pathlib import Path

    w = _command_name()
    if not Path(path).exists():
        if Path(f"{path}.part").exists():  # the writer could not finish it
            return [f"the recording was not finished: {path}.part",
                    f"  {w} recover {shlex.quote(path + '.part')}      makes a complete copy"]
        return [f"no recording was written to {path}"]
    c, q = shlex.quote(w), shlex.quote(path)
    sim = f"{c} sim --port 5000" + (f" --seed {seed}" if seed is not None else "")
    return [f"recorded {path}",
            f"  {c} analyze {q}      conformance report",
            f"  {c} cat {q}          every frame, decoded",
            f"  {c} tui {q}          browse it again (r: replay it from the TUI)",
            f"  {c} replay {q} --target HOST:PORT --password {shlex.quote(password)}",
            f"                                replay it against a server, such as: {sim}"]


def _announce_faults(middle: MiddleSettings) -> None:
    """Each fault the live proxy starts with, in words, on stderr before the
    app takes the screen (``record`` prints the same); a fault file that does
    not read, or a fault refused, is one line here rather than in the app."""
    from whiztap.analyzer.mitm.spec import FaultSpecError
    from whiztap.analyzer.protocol.text import printable
    from whiztap.sniffer.mitm.controller import ControlError, Controller, add_start_faults
    from whiztap.sniffer.record.summary import fault_lines

    controller = Controller()
    try:
        add_start_faults(controller, middle.fault_files, middle.faults)
    except (FaultSpecError, ControlError) as e:
        fail(str(e))
    for line in fault_lines(controller.faults):
        click.echo(printable(line), err=True)


def _quiet_faults(source: LiveSource) -> None:
    """The faults that chose no frame, said once the app is gone (its own
    notice of them went with the screen)."""
    from whiztap.analyzer.protocol.text import printable

    summary = source.recording.summary if source.recording is not None else None
    for fault in (summary or {}).get("quiet_faults", ()):
        click.echo(printable(f"warning: fault {fault} chose no frame"), err=True)


def _failed(app: WhiztapApp) -> None:
    """The app broke unexpectedly: one line and exit status 2, after the hints
    said where the recording is (the app finished it first)."""
    if app.failure is not None:
        error = app.failure
        said = str(error).splitlines()[0] if str(error) else ""
        fail(f"the TUI stopped on an unexpected error: {type(error).__name__}: {said} "
             "(set WHIZTAP_DEBUG=1 to see where; please report it)")


def _command_name() -> str:
    """How to run whiztap from here: its name if it is on PATH (an activated
    venv, a pipx install), else the path of the one running (after 'make',
    .venv/bin/whiztap)."""
    import os
    import shutil

    running = os.path.realpath(sys.argv[0])
    found = shutil.which("whiztap")
    if found and os.path.realpath(found) == running:
        return "whiztap"
    relative = os.path.relpath(running)
    return relative if not relative.startswith("..") else running


@click.command("tui")
@click.argument("path", required=False, metavar="[RECORDING]")
@click.option("--follow", metavar="FILE.mcap.part", default=None,
              help="Follow a recording that 'whiztap record' is writing.")
@click.option("--upstream", type=Address(), metavar="HOST:PORT", default=None,
              help="Live: run the recording proxy in the app, in front of this server.")
@click.option("--listen", type=Address("127.0.0.1"), metavar="[HOST:]PORT", default="127.0.0.1:6000", show_default=True,
              help="Live: where clients connect.")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default=None,
              help="Live: the recording to write [default: whiztap-DATE-TIME.mcap].")
@click.option("--keep-secrets", is_flag=True, help="Live: record and show the password as sent.")
@click.option("--force", is_flag=True, help="Live: write over a recording of the same name (never over an input).")
@click.option("--mirror", type=Address(), metavar="HOST:PORT", default=None,
              help="Live: also send each client's bytes to this server and show where its answers differ.")
@checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules').")
@foxglove_option
@middle_options
@limits_options
@assumed_map_options
def tui_command(path: str | None, follow: str | None, upstream: tuple[str, int] | None, listen: tuple[str, int],
                output: str | None, keep_secrets: bool, force: bool, mirror: tuple[str, int] | None, checksum_rule: str,
                foxglove: tuple[str, int] | None, answer_timeout: float, max_frame: int, max_image: int,
                channel_map: str | None, assume_config: str | None, **middle: Any) -> None:
    """Frames decoded and checked as they pass: a recording, live traffic, or a
    recording being written.

    \b
    whiztap tui FILE.mcap                               browse a recording
    whiztap tui --upstream HOST:PORT [--listen ADDR] [-o FILE.mcap] [--foxglove]
                                                        live, through the proxy
    whiztap tui --follow FILE.mcap.part                 follow 'whiztap record'

    Live, the proxy stands in the middle: i holds frames for you to accept,
    edit or drop, I injects one, f lists the faults in force and adds more
    (--fault, --faults, --script start with some; docs/faults.md).

    Press ? in the app for its keys.
    """
    if sum(x is not None for x in (path, follow, upstream)) != 1:
        fail("give one of: a recording FILE.mcap, --follow FILE.mcap.part, or --upstream HOST:PORT")
    if (foxglove is not None or mirror is not None) and upstream is None:
        fail("--foxglove and --mirror are for live traffic: they go with --upstream HOST:PORT")
    if middle_given(**middle) and upstream is None:
        fail("--fault, --faults, --control, --script, --seed and --hold-timeout drive the live proxy: "
             "they go with --upstream HOST:PORT")
    rule = checksum_rule
    limits = limits_assuming(limits_from(answer_timeout, max_frame, max_image), channel_map, assume_config)
    from whiztap.tui.data.sources import FileSource, FollowSource, LiveSource, ProxyRig, default_output, follow_path

    source: Source
    if path is not None:
        source = FileSource(_one_recording(path))
    elif follow is not None:
        follow = follow_path(follow)
        _check_recording(follow)
        source = FollowSource(follow)
    else:
        from whiztap.sniffer.record.record_run import RecordSettings

        assert upstream is not None  # one of the three, as checked above
        output = output or default_output()
        check_recording_output(output, split=False, force=force)
        settings = RecordSettings(listen, upstream, output,
                                  keep_secrets=keep_secrets, checksum_rule=rule, quiet=True, limits=limits,
                                  foxglove=foxglove, middle=middle_settings(**middle, always=True), mirror=mirror)
        _announce_faults(settings.middle)
        source = LiveSource(ProxyRig(settings), "live", redact_passwords=not keep_secrets)
    _need_terminal("whiztap tui")
    from whiztap.tui.app import WhiztapApp

    app = WhiztapApp(source, checksum_rule=rule, limits=limits)
    app.run()
    if app.error:
        fail(app.error)
    if isinstance(source, LiveSource):
        _quiet_faults(source)
        for line in _hints(source.rig.output):
            click.echo(line)
    _failed(app)


@click.command("demo")
@click.option("--headless", is_flag=True, help="No TUI: run, then print the conformance report.")
@click.option("--seconds", type=click.FloatRange(min=0.1), default=None, metavar="N",
              help=f"Stop after N seconds [headless default: {HEADLESS_SECONDS:g}; the TUI runs until q].")
@click.option("-o", "--output", type=click.Path(dir_okay=False), default="demo.mcap", show_default=True,
              help="The recording to write.")
@force_option
@foxglove_option
@middle_options
def demo_command(headless: bool, seconds: float | None, output: str, force: bool,
                 foxglove: tuple[str, int] | None, **middle: Any) -> None:
    """The whole tool on an embedded robot: the simulator, the recording proxy in
    front of it, and a scripted client using every command of the spec (with a
    few deliberate violations), shown live in the TUI and recorded.

    Without a terminal (or with --headless) it runs for a few seconds and prints
    the conformance report.  Exit status 0 when the demo ran, whatever the
    report says (its violations are deliberate); 2 when it could not run.

    The proxy stands in the middle, as in 'whiztap tui --upstream': --fault,
    --faults and --script act on the demo's traffic, and the TUI's keys hold,
    edit, drop and inject frames (docs/faults.md).
    """
    check_output(output, force=force, recording=True)
    settings = middle_settings(**middle, always=True)
    _announce_faults(settings)
    if not headless and not (sys.stdin.isatty() and sys.stdout.isatty()):
        seconds = seconds or HEADLESS_SECONDS
        click.echo(f"whiztap demo: no terminal, so no TUI: running headless for {seconds:g} s "
                   f"(whiztap demo --headless)")
        headless = True
    if headless:
        _headless(output, seconds or HEADLESS_SECONDS, foxglove, settings)
        return
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.data.sources import LiveSource
    from whiztap.tui.demo import PASSWORD, SEED, DemoRig

    source = LiveSource(DemoRig(output, foxglove, settings), "demo", redact_passwords=True)
    app = WhiztapApp(source, quit_after=seconds)
    app.run()
    if app.error:
        fail(app.error)
    _quiet_faults(source)
    for line in _hints(output, PASSWORD, SEED):
        click.echo(line)
    _failed(app)


def _headless(output: str, seconds: float, foxglove: tuple[str, int] | None, middle: MiddleSettings) -> None:
    import asyncio
    from pathlib import Path

    from whiztap.analyzer.analysis.report.content import build
    from whiztap.analyzer.cli.analyze import analyse_file, render
    from whiztap.analyzer.mitm.spec import FaultSpecError
    from whiztap.sniffer.mitm.scripts import ScriptError
    from whiztap.sniffer.record.feed import WriterError
    from whiztap.sniffer.record.record_run import StartError
    from whiztap.tui.demo import DELIBERATE_RULES, PASSWORD, SEED, run_headless

    try:
        client_error = asyncio.run(run_headless(output, seconds, foxglove, middle,
                                                announce=lambda line: click.echo(f"whiztap demo: {line}")))
    except (WriterError, FaultSpecError, ScriptError, StartError) as e:
        fail(str(e))
    except OSError as e:
        fail(f"the demo could not start: {e.strerror or e}")
    if client_error:
        click.echo(f"whiztap demo: the demo client stopped early: {client_error}", err=True)
    analysis = analyse_file(Path(output), "dev-sum")
    report = build(analysis)
    text = render(report, analysis, "text", to_terminal=sys.stdout.isatty())
    if text:
        click.echo(text, nl=not text.endswith("\n"))
    click.echo(f"The demo breaks these rules on purpose: {', '.join(DELIBERATE_RULES)}.")
    for line in _hints(output, PASSWORD, SEED):
        click.echo(line)
