"""``whiztap ctl``: drive a running ``whiztap record --control`` from the
command line, through its JSON control API (``whiztap.sniffer.mitm.http_api``).

Only the standard library talks to the API (urllib), so this command costs
nothing to load; the API's own one-line errors are shown as they come.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from typing import Any, NoReturn
from urllib.parse import quote

import click

from whiztap.analyzer.cli.errors import fail
from whiztap.analyzer.cli.output import output_stream, say
from whiztap.sniffer.cli.params import Address

TIMEOUT_S = 10.0


class Api:
    """The control API at ``address``: one JSON request, one JSON answer."""

    def __init__(self, address: tuple[str, int] | None, fmt: str) -> None:
        from whiztap.sniffer.nettext import show_address

        self.where = show_address(*address) if address is not None else None
        self.fmt = fmt

    def call(self, method: str, path: str, body: dict[str, Any] | None = None) -> Any:
        """The answer's JSON; any failure is one line and exit status 2."""
        import urllib.error
        import urllib.request

        if self.where is None:  # checked here, not by click, so that every subcommand's --help works without it
            fail("say where the control API is: --control [HOST:]PORT or WHIZTAP_CONTROL (see 'whiztap ctl --help')")
        data = None if body is None else json.dumps(body).encode()
        request = urllib.request.Request(f"http://{self.where}{path}", data=data, method=method,
                                         headers={"Content-Type": "application/json"})
        try:
            with urllib.request.urlopen(request, timeout=TIMEOUT_S) as reply:  # noqa: S310 - http only
                return json.loads(reply.read() or b"null")
        except urllib.error.HTTPError as e:
            fail(_error_text(e.code, e.read()))
        except urllib.error.URLError as e:
            self._unreachable(e.reason)
        except OSError as e:  # a timeout or a reset after connecting
            self._unreachable(e)
        except ValueError as e:
            fail(f"the control API at {self.where} answered something that is not JSON: {e}")

    def _unreachable(self, why: object) -> NoReturn:
        from whiztap.sniffer.nettext import reason

        text = reason(why) if isinstance(why, OSError) else str(why)
        if isinstance(why, TimeoutError):
            text = f"no answer within {TIMEOUT_S:g} s"
        fail(f"cannot reach the control API at {self.where}: {text[:1].lower()}{text[1:]}; "
             f"is 'whiztap record --control' running there?")

    def show(self, answer: Any, lines: list[str]) -> None:
        """The answer as JSON (``--format json``) or as ``lines`` of text."""
        if self.fmt == "json":  # JSON escapes control characters itself; say() would escape its line breaks
            with output_stream(None) as out:
                out.write(json.dumps(answer, indent=2) + "\n")
        else:
            for line in lines:
                say(line)


def _error_text(status: int, body: bytes) -> str:
    try:
        return str(json.loads(body)["error"])
    except (ValueError, KeyError, TypeError):
        return f"the control API answered HTTP {status}"


# -- how the API's objects read as text ------------------------------------------------------


def fault_line(f: dict) -> str:
    return f"#{f['id']} {f['name']}  {'on' if f['enabled'] else 'off'}  hits {f['hits']}  {f['spec']}"


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
@click.option("--control", type=Address("127.0.0.1", "--control"), envvar="WHIZTAP_CONTROL", metavar="[HOST:]PORT",
              help="The control API, as given to 'whiztap record --control' (or set WHIZTAP_CONTROL).  "
                   "[required]")
@click.option("--format", "fmt", type=click.Choice(["text", "json"]), default="text", show_default=True,
              help="Text lines, or the API's JSON as it answered.")
@click.pass_context
def ctl_command(ctx: click.Context, control: tuple[str, int] | None, fmt: str) -> None:
    """Drive a running 'whiztap record --control': faults, interception, held
    frames, injection.

    \b
    Example:
      whiztap record --upstream robot:5000 -o run.mcap --control 7000
      whiztap ctl --control 127.0.0.1:7000 fault add 'drop dir:s2c kind:response every:2'
      export WHIZTAP_CONTROL=127.0.0.1:7000; whiztap ctl state
    """
    ctx.obj = Api(control, fmt)


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
@click.argument("held_id", metavar="ID", type=int)
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
@click.argument("held_id", metavar="ID", type=int)
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
    api.show(answer, [f"released {answer['released']} held frame(s)"])


@ctl_command.command("inject")
@click.argument("conn", type=int)
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
