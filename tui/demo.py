"""``whiztap demo``: the whole tool on an embedded robot.

The simulator (winsock mode, password ``progwhiz``), the recording proxy in
front of it writing ``demo.mcap``, and a scripted client that uses every
command of the spec, then keeps a robot busy: sensor polling, servo moves
watched until they arrive, switches, scripts, camera images.  A few frames
break the spec on purpose, so there are violations to look at: a Set
Configuration with a wrong checksum, a channel out of range, a Servo Position
Request to a sensor, a number with a leading zero, stray bytes; and a second
client gives a wrong password.
"""

from __future__ import annotations

import asyncio
import contextlib
import dataclasses
from collections.abc import Callable
from typing import TYPE_CHECKING

from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, SENDCHKPASS
from whiztap.sniffer.sim.client import Client, ClientError
from whiztap.sniffer.sim.tour import SPEC_EXAMPLE_ENTRIES, every_command

if TYPE_CHECKING:
    from whiztap.sniffer.record.record_run import MiddleSettings, Recording
    from whiztap.sniffer.sim.simulator import Simulator
    from whiztap.tui.data.sources import Tap

LOCAL = "127.0.0.1"
PASSWORD = "progwhiz"
SEED = 7
PACE_S = 0.05  # between the demo client's requests: a few dozen frames a second
# The deliberate violations, as raw bytes the client library would never send.
DELIBERATE = (
    (b"rr1-31--0--2-ss1", "PW-RANGE-CHANNEL"),  # channel 31 does not exist
    (b"rr1-20--0--2-ss1", "PW-UNIT-MISMATCH"),  # a Servo Position Request to sensor 20
    (b"rr1-1--0700--0-ss1", "PW-SYNTAX-LEADING-ZERO"),  # served, with a warning
    (b"hello robot", "PW-FRAME-GARBAGE"),
)
# ... and what follows from them: the server ignores both requests, so they go unanswered.
DELIBERATE_RULES = ("PW-SETCFG-CHECKSUM", *(rule for _, rule in DELIBERATE), "PW-CHANNEL-UNCONFIGURED",
                    "PW-HS-AFTER-FAILED",
                    "PW-PAIR-UNANSWERED")


async def every_command_with_mistakes(client: Client) -> None:
    """Every command of the spec once, then the deliberate violations."""
    await every_command(client)
    await client.set_configuration(SPEC_EXAMPLE_ENTRIES, checksum=73)  # a wrong one: PW-SETCFG-CHECKSUM
    for data, _rule in DELIBERATE:
        await client.send_raw(data)
        await asyncio.sleep(PACE_S)


async def busy_robot(client: Client, stop: asyncio.Event) -> None:
    """Poll sensors, move servos and watch them travel, toggle a switch; an
    image now and then; until ``stop`` is set."""
    targets = (200, 1800, 1000, 600, 1400)
    n = 0
    while not stop.is_set():
        if n % 20 == 0:
            await client.normal_send(n // 20 % 3, targets[n // 20 % len(targets)])
        for channel in (12, 13, 14, 15):
            await client.sensor(channel)
        for channel in (0, 1, 2):
            await client.servo_position(channel)
        if n % 10 == 0:
            await (client.activate_switch(7) if n // 10 % 2 == 0 else client.deactivate_switch(7))
        if n % 50 == 25:
            await client.fetch_camera_image()
        n += 1
        await asyncio.sleep(PACE_S)


async def wrong_password(port: int) -> None:
    """A client that gets the password wrong, then sends a command anyway."""
    reader, writer = await asyncio.open_connection(LOCAL, port)
    try:
        await asyncio.wait_for(reader.readexactly(len(SENDCHKPASS)), 5)
        writer.write(b"not-the-password")
        await writer.drain()
        await asyncio.wait_for(reader.readexactly(len(FAILED_VALIDATION)), 5)
        writer.write(b"rr1-24--0--0-ss1")  # after Failed Validation: PW-HS-AFTER-FAILED
        await writer.drain()
        await asyncio.sleep(0.1)
    except (OSError, asyncio.IncompleteReadError, TimeoutError):
        pass
    finally:
        writer.close()
        with contextlib.suppress(OSError):
            await writer.wait_closed()


async def demo_client(port: int, stop: asyncio.Event) -> None:
    """What the demo's robot client does, until ``stop`` is set."""
    await wrong_password(port)
    async with await Client.connect(LOCAL, port, password=PASSWORD) as client:
        await every_command_with_mistakes(client)
        await busy_robot(client, stop)


class DemoRig:
    """Simulator, recording proxy and demo client: ``start()`` returns the Recording.

    The proxy always stands in the middle (``middle``, with ``always`` set),
    so the TUI's keys can hold, edit, drop and inject the demo's frames."""

    def __init__(self, output: str, foxglove: tuple[str, int] | None = None,
                 middle: MiddleSettings | None = None) -> None:
        from whiztap.sniffer.record.record_run import MiddleSettings

        self.output = output
        self.foxglove = foxglove  # (host, port): serve it live to the Foxglove app too
        self.middle = dataclasses.replace(middle or MiddleSettings(), always=True)
        self.simulator: Simulator | None = None
        self.recording: Recording | None = None
        self.client: asyncio.Task | None = None
        self.client_error: str | None = None
        self._stop_client = asyncio.Event()

    async def start(self, tap: Tap | None) -> Recording:
        from whiztap.sniffer.record.record_run import Recording, RecordSettings
        from whiztap.sniffer.sim.simulator import Simulator

        self.simulator = simulator = Simulator(mode="winsock", password=PASSWORD, seed=SEED)
        await simulator.start()
        self.recording = recording = Recording(
            RecordSettings((LOCAL, 0), (LOCAL, simulator.port), self.output, quiet=True, foxglove=self.foxglove,
                           middle=self.middle),
            consumers=[tap] if tap is not None else [], warn=tap.warn if tap is not None else None)
        try:
            await recording.start()
        except BaseException:
            await simulator.close()
            raise
        self.client = asyncio.get_running_loop().create_task(self._client(recording.port))
        return recording

    async def _client(self, port: int) -> None:
        try:
            await demo_client(port, self._stop_client)
        except (ClientError, OSError) as e:
            self.client_error = str(e)

    async def stop(self) -> dict | None:
        """Stop the client, finish the recording, stop the robot; the writer's summary."""
        if self.client is not None:
            # Ask first: on Python 3.11 a cancel that lands as a request's answer
            # arrives can be swallowed by asyncio.wait_for inside the client.
            self._stop_client.set()
            while not self.client.done():
                await asyncio.wait({self.client}, timeout=1.0)
                self.client.cancel()
            await asyncio.gather(self.client, return_exceptions=True)
        summary = None
        if self.recording is not None and self.recording.writer is not None:
            summary = await self.recording.stop("demo finished")
        if self.simulator is not None:
            await self.simulator.close()
        return summary


async def run_headless(output: str, seconds: float, foxglove: tuple[str, int] | None = None,
                       middle: MiddleSettings | None = None,
                       announce: Callable[[str], None] | None = None) -> str | None:
    """The demo without a screen for ``seconds``; the client's error, if it had
    one.  ``announce`` is told where the Foxglove app connects (``foxglove:
    URL``) and where the control API is (``control: ...``), with either asked
    for; ``middle`` (a MiddleSettings) adds faults, scripts or the control API."""
    rig = DemoRig(output, foxglove, middle)
    recording = await rig.start(tap=None)
    if recording.foxglove_url and announce is not None:
        announce(f"foxglove: {recording.foxglove_url}")
    if recording.control_text and announce is not None:
        announce(f"control: {recording.control_text}")
    try:
        await asyncio.sleep(seconds)
    finally:
        await rig.stop()
    return rig.client_error
