"""``whiztap sim`` and ``whiztap client``: the simulator and the client by hand.

Imports stay light at module level (``whiztap --help`` loads this module); the
simulator, which brings in Pillow for the camera, is imported when it runs.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from typing import TYPE_CHECKING

import click

from whiztap.analyzer.protocol.checksum import CHECKSUM_RULES, DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.cli.errors import fail
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS
from whiztap.sniffer.cli.params import Address
from whiztap.sniffer.cli.run import run, stop_signals
from whiztap.sniffer.nettext import reason, show_address
from whiztap.sniffer.sim.robot import DEFAULT_PASSWORD, DEFAULT_SERVO_SPEED

if TYPE_CHECKING:
    from whiztap.sniffer.sim.client import Client
    from whiztap.sniffer.sim.simulator import Simulator

DEFAULT_PORT = 5000
CRASHED = 70  # exit status after a planted bug crashed the server (EX_SOFTWARE)
_LOG_LEVELS = (logging.WARNING, logging.INFO, logging.DEBUG)


@click.command("sim")
@click.option("--host", default="127.0.0.1", show_default=True, help="Address to listen on.")
@click.option("--port", type=click.IntRange(0, 65535), default=DEFAULT_PORT, show_default=True,
              help="Port to listen on; 0 picks a free one (printed).")
@click.option("--mode", type=click.Choice(["winsock", "vpn"]), default="winsock", show_default=True,
              help="winsock: password handshake first; vpn: no handshake.")
@click.option("--password", default=DEFAULT_PASSWORD, show_default=True, help="Password in winsock mode.")
@click.option("--channels", default=DEFAULT_CHANNELS, show_default=True,
              help="Unit per channel: servo, sensor, switch (type 0) or switch1 (type 1) with ranges.")
@click.option("--seed", type=int, default=0, show_default=True, help="Seeds the sensor signals and the faults.")
@click.option("--servo-speed", type=click.FloatRange(min=0, min_open=True), default=DEFAULT_SERVO_SPEED,
              show_default=True, help="Servo travel in position units (0-2000) per second.")
@click.option("--camera", type=click.Choice(["test", "none"]), default="test", show_default=True,
              help="test: answer Fetch Camera Image with a JPEG test picture; none: no answer.")
@click.option("--checksum-rule", type=click.Choice(sorted(CHECKSUM_RULES)), default=DEFAULT_CHECKSUM_RULE,
              show_default=True, help="How Set Configuration checksums are verified.")
@click.option("--latency", type=click.FloatRange(min=0), default=0.0, metavar="MS", help="Delay every reply.")
@click.option("--jitter", type=click.FloatRange(min=0), default=0.0, metavar="MS",
              help="Vary the delay by up to this much either way.")
@click.option("--drop-rate", type=click.FloatRange(0, 1), default=0.0, metavar="P",
              help="Probability that an answer is not sent.")
@click.option("--split", is_flag=True, help="Write every reply in random small pieces.")
@click.option("--garbage-rate", type=click.FloatRange(0, 1), default=0.0, metavar="P",
              help="Probability of stray bytes before a reply.")
@click.option("--bug", "bugs", multiple=True, metavar="NAME",
              help="Plant a server defect for a conformance suite to catch (repeatable; --bugs lists them).")
@click.option("--bugs", "list_bugs", is_flag=True, help="List the planted bugs --bug takes, and exit.")
@click.option("-v", "--verbose", count=True, help="-v logs every line break and more.")
@click.option("-q", "--quiet", is_flag=True, help="Log only problems, not connections.")
def sim_command(host: str, port: int, mode: str, password: str, channels: str, seed: int, servo_speed: float,
                camera: str, checksum_rule: str, latency: float, jitter: float, drop_rate: float, split: bool,
                garbage_rate: float, bugs: tuple[str, ...], list_bugs: bool, verbose: int, quiet: bool) -> None:
    """Run a simulated Progwhiz Robotics Server (Rev 1.8) until interrupted.

    With --bug it misbehaves on purpose; a bug that crashes it ends it with
    exit status 70 and the line 'whiztap sim: crashed (planted bug NAME)'.
    """
    from whiztap.sniffer.sim.bugs import BugError, listing
    from whiztap.sniffer.sim.channels import ChannelSpecError
    from whiztap.sniffer.sim.faults import FaultConfig
    from whiztap.sniffer.sim.simulator import Simulator

    if list_bugs:
        click.echo(listing())
        return
    if mode == "winsock" and not password:
        fail("winsock mode needs a non-empty --password")
    try:
        faults = FaultConfig(latency, jitter, drop_rate, split, garbage_rate)
        sim = Simulator(host, port, mode=mode, password=password, channels=channels, seed=seed,
                        servo_speed=servo_speed, camera=camera == "test", checksum_rule=checksum_rule,
                        faults=faults, bugs=bugs)
    except BugError as e:
        fail(f"--bug: {e}")
    except (ChannelSpecError, ValueError) as e:
        fail(f"--channels: {e}" if isinstance(e, ChannelSpecError) else str(e))
    level = logging.WARNING if quiet else _LOG_LEVELS[min(1 + verbose, 2)]
    logging.basicConfig(stream=sys.stderr, level=level, format="%(asctime)s %(message)s", datefmt="%H:%M:%S")
    if run(_run_sim(sim)):
        click.echo(f"whiztap sim: crashed (planted bug {sim.crash_reason})", err=True)
        sys.exit(CRASHED)


async def _run_sim(sim: Simulator) -> bool:
    """Serve until told to stop; True if a planted bug crashed the server."""
    try:
        await sim.start()
    except OSError as e:
        fail(f"cannot listen on {show_address(sim.host, sim.requested_port)}: {e.strerror or e}")
    import asyncio

    stopped = asyncio.Event()
    # Ctrl-C, SIGTERM and SIGHUP are how a server is meant to end: exit 0, as record and stub do
    try:
        with stop_signals(stopped.set):
            where = ", ".join(show_address(host, port) for host, port in sim.addresses)
            planted = f", planted bugs: {', '.join(sim.bugs)}" if sim.bugs else ""
            click.echo(f"whiztap sim: listening on {where} ({sim.mode}, {len(sim.robot.channels)} channels, "
                       f"seed {sim.seed}{planted})")
            stop = asyncio.create_task(stopped.wait())
            crash = asyncio.create_task(sim.crashed.wait())
            await asyncio.wait((stop, crash), return_when=asyncio.FIRST_COMPLETED)
            stop.cancel()
            crash.cancel()
    finally:
        await sim.close()
    return sim.crashed.is_set()


@click.command("client", context_settings={"ignore_unknown_options": True})
@click.argument("address", type=Address(what="the server address"), metavar="HOST:PORT")
@click.argument("words", nargs=-1, type=click.UNPROCESSED, metavar="[COMMAND]...")
@click.option("--password", "-p", default=None,
              help="Do the winsock handshake with this password (or set WHIZTAP_PASSWORD, which ps does not show).")
@click.option("--timeout", type=click.FloatRange(min=0, min_open=True), default=5.0, show_default=True,
              help="Seconds to wait for a connection, the handshake and each answer.")
@click.option("--raw", is_flag=True,
              help="Send commands even when their frame breaks the spec (a channel or value out of range).")
@click.option("--no-config", is_flag=True,
              help="With a COMMAND: do not fetch the configuration before it (the spec asks a client to).")
def client_command(address: tuple[str, int], words: tuple[str, ...], password: str | None, timeout: float,
                   raw: bool, no_config: bool) -> None:
    """Send commands to a Progwhiz server (or a proxy in front of one).

    One COMMAND on the command line (e.g. 'sensor 12', 'servo 3 1500',
    'switch 7 on', 'script 120', 'config', 'camera -o pic.jpg', 'raw TEXT' or a
    frame such as 'rr1-12--0--0-ss1'), quoted or not: it is read as the same
    line typed at the prompt.  Without one, a command per line from standard
    input ('help' lists them).

    A command whose frame would break the spec (sensor 99, servo 3 99999) is
    refused before anything is sent, naming the rule; --raw sends it anyway,
    and a frame typed as escaped text (raw TEXT, rr1-...) is always sent as is.
    The password may also come from WHIZTAP_PASSWORD (not shown by ps).
    With a COMMAND, the configuration is fetched first, as the spec asks of a
    client (the server's channel map then resolves every later frame);
    --no-config skips it.  At the prompt, what is typed is sent.
    """
    host, port = address
    if password is None:
        password = os.environ.get("WHIZTAP_PASSWORD") or None
    sys.exit(run(_run_client(host, port, password, timeout, list(words), not raw, not no_config)))


async def _run_client(host: str, port: int, password: str | None, timeout: float, words: list[str],
                      validate: bool, fetch_config: bool = True) -> int:
    from whiztap.sniffer.sim.client import Client, ClientError
    from whiztap.sniffer.sim.console import CommandError, run, split_line

    words = split_line(" ".join(words))  # 'sensor 12' and sensor 12 alike, as at the prompt
    try:
        client = await Client.connect(host, port, password, timeout)
    except ClientError as e:
        fail(f"{show_address(host, port)}: {e}")
    except OSError as e:
        fail(f"cannot connect to {show_address(host, port)}: {reason(e)}")
    client.validate = validate
    async with client:
        # one command: fetched first, as the spec asks ('config' is that fetch); at the prompt the user says
        if fetch_config and words and words[0].lower() != "config":
            try:
                await client.fetch_configuration()
            except ClientError as e:
                fail(f"{show_address(host, port)}: fetching the configuration first: {e} "
                     "(--no-config skips it)")
        if words:
            try:
                click.echo(await run(client, words))
            except (CommandError, ClientError) as e:
                fail(str(e))
            return 0
        return await _repl(client)


async def _repl(client: Client) -> int:
    import asyncio

    from whiztap.sniffer.sim.client import ClientError, ConnectionClosed, HandshakeError
    from whiztap.sniffer.sim.console import CommandError, item_line, run, split_line

    lines: asyncio.Queue[str] = asyncio.Queue()
    loop = asyncio.get_running_loop()

    def read_stdin() -> None:  # a daemon thread: a blocked readline must not hold up exit
        for line in sys.stdin:
            loop.call_soon_threadsafe(lines.put_nowait, line)
        loop.call_soon_threadsafe(lines.put_nowait, "")

    threading.Thread(target=read_stdin, daemon=True).start()
    interactive = sys.stdin.isatty()
    failures = shown = 0
    while True:
        for item in client.stray[shown:]:
            click.echo(f"{item_line(item)}  (unsolicited)")
        shown = len(client.stray)
        if interactive:
            click.echo("> ", nl=False)
        line = await lines.get()
        if not line:
            break
        words = split_line(line)
        if not words or words[0].startswith("#"):
            continue
        if words[0].lower() in ("quit", "exit"):
            break
        try:
            click.echo(await run(client, words))
        except (ConnectionClosed, HandshakeError) as e:
            fail(str(e))
        except (CommandError, ClientError) as e:
            failures += 1
            click.echo(f"error: {e}", err=True)
    return 1 if failures else 0
