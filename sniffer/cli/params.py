"""Options of the sniffer's commands: network addresses, and the options of
every command that writes a recording (record, capture) with its output check."""

from __future__ import annotations

from collections.abc import Callable
from typing import TYPE_CHECKING, Any

import click
from click.core import ParameterSource

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import check_output
from whiztap.analyzer.cli.params import ByteSize, checksum_rule_option, force_option
from whiztap.sniffer.mitm.control_endpoint import DEFAULT as CONTROL_DEFAULT  # --control alone

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.control_endpoint import Endpoint
    from whiztap.sniffer.record.live_gate import LiveAddress
    from whiztap.sniffer.record.record_run import MiddleSettings


class Address(click.ParamType):
    """HOST:PORT, [V6]:PORT, or PORT alone when there is a default host; the
    value is (host, port).  ``what`` names it in a message (default: the option)."""

    name = "address"

    def __init__(self, default_host: str | None = None, what: str | None = None) -> None:
        self.default_host = default_host
        self.what = what

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> tuple[str, int]:
        if isinstance(value, tuple):
            return value
        from whiztap.sniffer.nettext import AddressError, parse_address

        what = self.what or (max(param.opts, key=len) if param is not None else "address")
        try:
            return parse_address(value, self.default_host, what)
        except AddressError as e:
            fail(str(e))


FOXGLOVE_DEFAULT = "127.0.0.1:8765"
HOLD_TIMEOUT_S = 60.0  # a held frame nobody acts on goes on as it is after this


_ORIGINS = "whiztap.foxglove_origins"


def _foxglove_origins(ctx: click.Context, param: click.Parameter, values: tuple[str, ...]) -> None:
    """--foxglove-origin, checked, kept for --foxglove (read first: it is eager)."""
    from whiztap.sniffer.record.live_gate import origin_text

    try:
        ctx.meta[_ORIGINS] = tuple(origin_text(v) for v in values)
    except ValueError as e:
        raise click.BadParameter(str(e), ctx, param) from None


def _foxglove_value(ctx: click.Context, param: click.Parameter, value: tuple[str, int] | None) -> LiveAddress | None:
    """--foxglove as a LiveAddress: where, and the web origins also allowed."""
    origins = ctx.meta.get(_ORIGINS, ())
    if value is None:
        if origins:
            raise click.UsageError("--foxglove-origin goes with --foxglove", ctx)
        return None
    from whiztap.sniffer.record.live_gate import LiveAddress

    return LiveAddress(*value, origins)


def foxglove_option(f: Callable) -> Callable:
    """--foxglove [HOST:]PORT: also serve the recording live to the Foxglove app
    (``whiztap.sniffer.record.live``); alone, on 127.0.0.1:8765.  With
    --foxglove-origin ORIGIN (repeatable), the web pages also allowed to read
    it; the value is one LiveAddress, so a command takes both as one."""
    f = click.option(
        "--foxglove-origin", "foxglove_origins", multiple=True, metavar="ORIGIN", is_eager=True,
        expose_value=False, callback=_foxglove_origins,
        help="Also let the web page at ORIGIN (https://HOST[:PORT]) read --foxglove; the Foxglove app "
             "(https://app.foxglove.dev) and pages on localhost may already; repeatable.")(f)
    return click.option(
        "--foxglove", type=Address("127.0.0.1"), is_flag=False, flag_value=FOXGLOVE_DEFAULT, default=None,
        metavar="[[HOST:]PORT]", callback=_foxglove_value,
        help=f"Also serve the traffic live to the Foxglove app (Foxglove WebSocket, the recording's topics); "
             f"alone: {FOXGLOVE_DEFAULT}.  Another host exposes the traffic to the network.")(f)


def recording_options(f: Callable) -> Callable:
    """Splitting, secrets, the checksum rule and --force: the options of every
    command that writes a recording."""
    options: list[Callable[[Callable], Callable]] = [
        click.option("--split-size", type=ByteSize(), default=None,
                     help="Start a new numbered file when this one reaches BYTES (e.g. 100M)."),
        click.option("--split-duration", type=click.FloatRange(min=0.001), default=None, metavar="SECONDS",
                     help="Start a new numbered file every SECONDS."),
        click.option("--keep-secrets", is_flag=True,
                     help="Record the password as sent (default: '*' bytes and <redacted>)."),
        checksum_rule_option("Set Configuration checksum rule (see 'whiztap rules')."),
        force_option,
    ]
    for option in reversed(options):
        f = option(f)
    return f


def check_recording_output(output: str, split: bool, force: bool, inputs: tuple[str, ...] = ()) -> None:
    """The output rule (whiztap.analyzer.recording.output_rule) for a recording: never over an
    input; not over a recording, or the ``.part`` a crashed one left (which
    'whiztap recover' could still save), unless --force.  A split recording
    refuses every numbered part already there at start, rather than stop when
    it reaches one hours later."""
    check_output(output, inputs, force=force, recording=True, split=split)
    if split and not force:
        from whiztap.analyzer.recording.sets import numbered_parts

        later = numbered_parts(output)
        if later:
            fail(f"{later[0]} exists (a part of another recording?); "
                 f"use --force to overwrite it or -o to choose another name")


class ControlParam(click.ParamType):
    """Where the control API is: a socket PATH, or TCP [HOST:]PORT (sniffer/mitm/control_endpoint.py)."""

    name = "control"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value
        from whiztap.sniffer.mitm.control_endpoint import EndpointError, parse_endpoint

        try:
            return parse_endpoint(value, "--control")
        except EndpointError as e:
            fail(str(e))


class FaultSpecParam(click.ParamType):
    """A fault SPEC (docs/faults.md), parsed at once: an unknown word is a usage error naming it."""

    name = "SPEC"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if not isinstance(value, str):
            return value
        from whiztap.analyzer.mitm.spec import FaultSpecError, parse_fault

        try:
            return parse_fault(value)
        except FaultSpecError as e:
            self.fail(str(e), param, ctx)


def middle_options(f: Callable) -> Callable:
    """The proxy as the man in the middle: faults, the control API, scripts
    (docs/faults.md).  Any of them puts every connection through the lanes."""
    for option in reversed([
        click.option("--fault", "faults", type=FaultSpecParam(), multiple=True,
                     help="A fault to apply (repeatable), e.g. 'delay:200ms dir:s2c' or "
                          "'drop dir:s2c kind:response every:2'; see docs/faults.md."),
        click.option("--faults", "fault_files", type=click.Path(dir_okay=False), multiple=True, metavar="FILE",
                     help="A TOML file of named faults ([faults.NAME] spec = \"...\")."),
        click.option("--control", type=ControlParam(), is_flag=False, flag_value=CONTROL_DEFAULT, default=None,
                     metavar="[PATH|[HOST:]PORT]",
                     help="Serve the JSON control API (faults, intercept, release, inject; 'whiztap ctl' "
                          "finds it): alone, on a Unix socket only you can open; PATH, on that socket; "
                          "[HOST:]PORT, on TCP with a bearer token (printed at start).  See docs/faults.md."),
        click.option("--control-token", envvar="WHIZTAP_CONTROL_TOKEN", default=None, metavar="TOKEN",
                     help="The token a TCP --control takes (or set WHIZTAP_CONTROL_TOKEN) [default: a new "
                          "one, printed at start]."),
        click.option("--script", "scripts", type=click.Path(dir_okay=False), multiple=True, metavar="FILE.py",
                     help="Hooks (frame, opened, closed) that may pass, drop, replace, delay or inject."),
        click.option("--seed", type=int, default=None, help="Seed for prob:, jitter: and slice ranges."),
        click.option("--hold-timeout", type=click.FloatRange(min=0.01), default=HOLD_TIMEOUT_S, show_default=True,
                     metavar="SECONDS", help="Release a held frame as it is after this long."),
    ]):
        f = option(f)
    return f


def middle_settings(faults: tuple, fault_files: tuple[str, ...], control: Endpoint | None, control_token: str | None,
                    scripts: tuple[str, ...], seed: int | None, hold_timeout: float,
                    always: bool = False) -> MiddleSettings:
    """The ``middle_options`` as the recording's MiddleSettings; ``always``
    puts the proxy in the middle even with none of them given (the TUI's live
    mode and the demo, whose keys drive it)."""
    from whiztap.sniffer.record.record_run import MiddleSettings

    return MiddleSettings(tuple(faults), tuple(fault_files), control_with_token(control, control_token),
                          tuple(scripts), seed, hold_timeout, always)


def control_with_token(control: Endpoint | None, token: str | None) -> Endpoint | None:
    """``--control``'s endpoint with ``--control-token`` in it: a TCP one's.  A
    Unix socket takes none (its folder is its lock): given on the command line
    with one, it is an error; from WHIZTAP_CONTROL_TOKEN (set for ctl, say), ignored."""
    if control is None or not token:
        return control
    if control.unix:
        if click.get_current_context().get_parameter_source("control_token") is ParameterSource.COMMANDLINE:
            fail("--control-token goes with a TCP --control [HOST:]PORT; a Unix socket needs no token")
        return control
    from dataclasses import replace

    from whiztap.sniffer.mitm.control_endpoint import EndpointError, check_token

    try:
        return replace(control, token=check_token(token, "--control-token"))
    except EndpointError as e:
        fail(str(e))


def middle_given(faults: tuple, fault_files: tuple[str, ...], control: Any, control_token: str | None,
                 scripts: tuple[str, ...], seed: int | None, hold_timeout: float) -> bool:
    """Whether any of the ``middle_options`` was given (a command that takes
    them only in one of its modes refuses them in the others)."""
    return bool(faults or fault_files or control or scripts or seed is not None or hold_timeout != HOLD_TIMEOUT_S)
