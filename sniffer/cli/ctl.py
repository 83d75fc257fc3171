"""``whiztap ctl``: drive a running ``whiztap record --control`` from the
command line, through its JSON control API (docs/faults.md).

The client (``whiztap.sniffer.mitm.control_client``) recognises the API
before it sends anything that matters, and reads answers up to a bound; the
API's own one-line errors are shown as they come.  ``--control``,
``--control-token`` and ``--format`` are taken before the subcommand or
after it, alike.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any
from urllib.parse import quote

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import output_stream, say
from whiztap.analyzer.protocol.text import plural

FORCE_HINT = "send it anyway with force"  # the controller's words; here the option is --force


class Api:
    """The control API the options name: one JSON request, one JSON answer."""

    def __init__(self) -> None:
        self.control: str | None = None  # --control or WHIZTAP_CONTROL, as typed
        self.control_token: str | None = None
        self.fmt = "text"
        self._client: Any = None  # a ControlClient, made at the first call

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """The answer's JSON; any failure is one line and exit status 2."""
        from whiztap.sniffer.mitm.control_client import ControlClientError

        if self._client is None:  # here, not in click, so that every subcommand's --help works without it
            self._client = self._connect()
        try:
            return self._client.call(method, path, body)
        except ControlClientError as e:
            fail(str(e).replace(FORCE_HINT, "send it anyway with --force"))

    def _connect(self) -> Any:
        """A client of the endpoint named, or of the one running for this user."""
        from whiztap.sniffer.mitm.control_client import ControlClient
        from whiztap.sniffer.mitm.control_endpoint import Endpoint, EndpointError, check_token, parse_endpoint

        try:
            if self.control:
                endpoint = parse_endpoint(self.control, "--control")
            else:
                endpoint = Endpoint(path=_running_socket())
            if self.control_token and not endpoint.unix:
                endpoint = Endpoint(host=endpoint.host, port=endpoint.port,
                                    token=check_token(self.control_token, "--control-token"))
        except EndpointError as e:
            fail(str(e))
        return ControlClient(endpoint)

    def show(self, answer: Any, lines: list[str]) -> None:
        """The answer as JSON (``--format json``) or as ``lines`` of text."""
        if self.fmt == "json":  # JSON escapes control characters itself; say() would escape its line breaks
            with output_stream(None) as out:
                out.write(json.dumps(answer, indent=2) + "\n")
        else:
            for line in lines:
                say(line)


def _running_socket() -> str:
    """The socket of the one control API this user runs with a bare
    ``--control``; one line naming what to do when there is none or several."""
    from whiztap.sniffer.mitm.control_endpoint import live_sockets, runtime_dir

    try:
        found = live_sockets()
    except OSError as e:
        fail(f"cannot look for a running control API in {runtime_dir()}: {e.strerror or e}")
    if len(found) == 1:
        return str(found[0])
    if not found:
        fail(f"no control API is running for you (none in {runtime_dir()}): start 'whiztap record --control', "
             f"or say where one is with --control PATH|[HOST:]PORT or WHIZTAP_CONTROL")
    fail(f"{len(found)} control APIs are running ({', '.join(p.name for p in found)} in {runtime_dir()}): "
         f"choose one with --control PATH")


def _setter(ctx: click.Context, param: click.Parameter, value: Any) -> Any:
    """An option's value onto the Api, whichever command it was given to."""
    if value is not None:
        setattr(ctx.ensure_object(Api), param.name, value)
    return value


def _options(top: bool) -> list[click.Option]:
    """The options every ctl command takes; the group's alone read the
    environment and have the defaults, so a subcommand's override only what is typed."""
    return [
        click.Option(["--control"], envvar="WHIZTAP_CONTROL" if top else None, metavar="PATH|[HOST:]PORT",
                     callback=_setter, expose_value=False,
                     help="The control API, as 'whiztap record --control' printed it (or set WHIZTAP_CONTROL) "
                          "[default: the one socket running for you]."),
        click.Option(["--control-token"], envvar="WHIZTAP_CONTROL_TOKEN" if top else None, metavar="TOKEN",
                     callback=_setter, expose_value=False,
                     help="A TCP control API's token, as printed at its start (or set WHIZTAP_CONTROL_TOKEN)."),
        click.Option(["--format", "fmt"], type=click.Choice(["text", "json"]), default="text" if top else None,
                     show_default=top, callback=_setter, expose_value=False,
                     help="Text lines, or the API's JSON as it answered."),
    ]


class Number(click.ParamType):
    """A count or an id: digits only, at most 18 (more is no id of the API's, and
    Python will not even turn thousands of digits into an int)."""

    name = "number"

    def convert(self, value: Any, param: click.Parameter | None, ctx: click.Context | None) -> Any:
        if isinstance(value, int):
            return value
        if not (value.isascii() and value.isdigit() and len(value) <= 18):
            shown = value if len(value) <= 20 else value[:20] + "..."
            self.fail(f"{shown!r} is not a number of at most 18 digits", param, ctx)
        return int(value)


# -- how the API's objects read as text ------------------------------------------------------


def fault_line(f: dict) -> str:
    """One fault as ``ctl`` lists it: what it chose (``matched``) beside what it did (``hits``), and its
    SPEC with what it means in words."""
    return (f"#{f['id']} {f['name']}  {'on' if f['enabled'] else 'off'}  matched {f['matched']}  hits {f['hits']}  "
            f"{f['spec']}  ({f['meaning']})")


def held_line(h: dict) -> str:
    return (f"#{h['id']} conn {h['conn']} {h['dir']} {h['kind']} {h['text']}  ({h['meaning']}; "
            f"waited {h['waited_s']:g} s, {h['cause']})")


def connection_line(c: dict) -> str:
    return f"#{c['conn']} from {c['client']}  queued c2s {c['c2s_queued']} B, s2c {c['s2c_queued']} B"


def state_lines(state: dict) -> list[str]:
    seed = state.get("seed")
    lines = [f"intercept: {state['intercept'] or '(off)'}", f"seed: {'(none)' if seed is None else seed}",
             f"scripts: {', '.join(state['scripts']) or '(none)'}", f"faults: {len(state['faults'])}"]
    lines += ["  " + fault_line(f) for f in state["faults"]]
    lines.append(f"held: {len(state['held'])}")
    lines += ["  " + held_line(h) for h in state["held"]]
    lines.append(f"connections: {len(state['connections'])}")
    lines += ["  " + connection_line(c) for c in state["connections"]]
    return lines


def _key(text: str) -> str:
    return quote(text, safe="")


def _fault_call(api: Api, method: str, path: str, body: dict[str, Any] | None, verb: str) -> None:
    """A request whose answer is one fault, shown as ``verb`` and its line."""
    fault = api.call(method, path, body)
    api.show(fault, [f"{verb}fault {fault_line(fault)}"])


def _listing(api: Api, path: str, key: str, line: Callable[[dict], str], none: str) -> None:
    """GET ``path``, whose answer lists ``key``: one line each, or ``none``."""
    answer = api.call("GET", path)
    api.show(answer, [line(item) for item in answer[key]] or [none])


# -- the commands -------------------------------------------------------------------------------


@click.group("ctl")
@click.pass_context
def ctl_command(ctx: click.Context) -> None:
    """Drive a running 'whiztap record --control': faults, interception, held
    frames, injection.

    With no --control, ctl finds the Unix socket that 'record --control'
    opened for you (one running at a time); a TCP one takes its token.

    \b
    Example:
      whiztap record --upstream robot:5000 -o run.mcap --control
      whiztap ctl fault add 'drop dir:s2c kind:response every:2'
      whiztap ctl held --format json
      whiztap ctl --control http://127.0.0.1:7000 --control-token TOKEN state
    """
    ctx.ensure_object(Api)


@ctl_command.group("fault")
def fault_group() -> None:
    """Add, list, remove, switch on or off the faults in force.

    \b
    Example:
      whiztap ctl fault add 'delay:200ms dir:s2c' --name slow
      whiztap ctl fault off slow
    """


@fault_group.command("add")
@click.argument("spec")
@click.option("--name", default="", help="A name to refer to it by (default: fault-ID).")
@click.pass_obj
def fault_add(api: Api, spec: str, name: str) -> None:
    """Apply the fault SPEC from now on (docs/faults.md).

    \b
    Example:
      whiztap ctl fault add 'drop dir:s2c kind:response ch:12 every:2' --name lossy
    """
    _fault_call(api, "POST", "/faults", {"spec": spec, "name": name or None}, "added ")


@fault_group.command("list")
@click.pass_obj
def fault_list(api: Api) -> None:
    """The faults in force, in the order they act.

    \b
    Example:
      whiztap ctl fault list
    """
    _listing(api, "/faults", "faults", fault_line, "no faults")


@fault_group.command("rm")
@click.argument("key", metavar="ID|NAME")
@click.pass_obj
def fault_rm(api: Api, key: str) -> None:
    """Remove a fault.

    \b
    Example:
      whiztap ctl fault rm lossy
    """
    _fault_call(api, "DELETE", f"/faults/{_key(key)}", None, "removed ")


def _switch(api: Api, key: str, enabled: bool) -> None:
    _fault_call(api, "POST", f"/faults/{_key(key)}/enable", {"enabled": enabled}, "")


@fault_group.command("on")
@click.argument("key", metavar="ID|NAME")
@click.pass_obj
def fault_on(api: Api, key: str) -> None:
    """Switch a fault back on.

    \b
    Example:
      whiztap ctl fault on 1
    """
    _switch(api, key, True)


@fault_group.command("off")
@click.argument("key", metavar="ID|NAME")
@click.pass_obj
def fault_off(api: Api, key: str) -> None:
    """Switch a fault off (it stays in the list; 'fault on' brings it back).

    \b
    Example:
      whiztap ctl fault off 1
    """
    _switch(api, key, False)


@ctl_command.command("intercept")
@click.argument("filter_text", metavar="[FILTER]", required=False)
@click.option("--off", is_flag=True, help="Hold nothing more (frames held now stay held).")
@click.pass_obj
def intercept(api: Api, filter_text: str | None, off: bool) -> None:
    """Hold the frames FILTER selects until released, edited or dropped;
    without FILTER, show the filter in force.  FILTER has the words of
    'whiztap cat --filter' (conn: dir: kind: ch: and text).

    \b
    Example:
      whiztap ctl intercept 'dir:c2s kind:command ch:12'
      whiztap ctl intercept --off
    """
    if off and filter_text:
        fail("give a FILTER or --off, not both")
    if off or filter_text is not None:
        answer = api.call("PUT", "/intercept", {"filter": "" if off else filter_text})
    else:
        answer = api.call("GET", "/intercept")
    api.show(answer, [f"intercept: {answer['filter'] or '(off)'}"])


@ctl_command.command("held")
@click.pass_obj
def held(api: Api) -> None:
    """The frames held now, oldest first.

    \b
    Example:
      whiztap ctl held
    """
    _listing(api, "/held", "held", held_line, "no held frames")


@ctl_command.command("release")
@click.argument("held_id", metavar="ID", type=Number())
@click.option("--edit", default=None, metavar="TEXT",
              help="Send this frame instead (escaped text like rr1-13--0--0-ss1, or console words like "
                   "'sensor 13').")
@click.option("--force", is_flag=True, help="Send the edit even if it breaks a rule of the spec.")
@click.pass_obj
def release(api: Api, held_id: int, edit: str | None, force: bool) -> None:
    """Let a held frame go, as it is or edited.

    \b
    Example:
      whiztap ctl release 3 --edit 'sensor 13'
    """
    answer = api.call("POST", f"/held/{held_id}/release", {"edit": edit, "force": force})
    api.show(answer, [f"released #{answer['id']} as {answer['text']}"])


@ctl_command.command("drop")
@click.argument("held_id", metavar="ID", type=Number())
@click.pass_obj
def drop(api: Api, held_id: int) -> None:
    """Drop a held frame: the other side never gets it.

    \b
    Example:
      whiztap ctl drop 3
    """
    answer = api.call("POST", f"/held/{held_id}/drop")
    api.show(answer, [f"dropped #{answer['id']} {answer['text']}"])


@ctl_command.command("release-all")
@click.pass_obj
def release_all(api: Api) -> None:
    """Let every held frame go as it is.

    \b
    Example:
      whiztap ctl release-all
    """
    answer = api.call("POST", "/held/release-all")
    api.show(answer, [f"released {plural(answer['released'], 'held frame')}"])


@ctl_command.command("inject")
@click.argument("conn", type=Number())
@click.argument("direction", metavar="c2s|s2c", type=click.Choice(["c2s", "s2c"]))
@click.argument("text")
@click.option("--force", is_flag=True, help="Send it even if it breaks a rule of the spec.")
@click.pass_obj
def inject(api: Api, conn: int, direction: str, text: str, force: bool) -> None:
    """Send a frame of your own on connection CONN: toward the server (c2s)
    or the client (s2c), after what is queued there.

    \b
    Example:
      whiztap ctl inject 1 c2s 'sensor 12'
      whiztap ctl inject 1 s2c 'cr1-12--500--0-ss1'
    """
    answer = api.call("POST", "/inject", {"conn": conn, "dir": direction, "frame": text, "force": force})
    api.show(answer, [f"injected {answer['frame']} on #{answer['conn']} {answer['dir']}"])


@ctl_command.command("connections")
@click.pass_obj
def connections(api: Api) -> None:
    """The connections open through the proxy, and what each direction holds back.

    \b
    Example:
      whiztap ctl connections
    """
    _listing(api, "/connections", "connections", connection_line, "no connections")


@ctl_command.command("state")
@click.pass_obj
def state(api: Api) -> None:
    """Everything at once: intercept filter, seed, scripts, faults, held frames, connections.

    \b
    Example:
      whiztap ctl --format json state
    """
    answer = api.call("GET", "/state")
    api.show(answer, state_lines(answer))


def _share_options(group: click.Group) -> None:
    """Every subcommand, at any depth, takes the group's options too."""
    for command in group.commands.values():
        command.params.extend(_options(top=False))
        if isinstance(command, click.Group):
            _share_options(command)


ctl_command.params.extend(_options(top=True))
_share_options(ctl_command)
