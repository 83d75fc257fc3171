"""The little command language of ``whiztap client``: words in, one line out.

Kept apart from the click command so it can be tested against a live simulator
without a subprocess, and used both for one command on the command line and for
lines read from standard input.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import decode
from whiztap.analyzer.protocol.frame_text import CONSOLE_WORDS, HEADERS, FrameTextError, message_from_words
from whiztap.analyzer.protocol.framing import Item
from whiztap.analyzer.recording.output_rule import OutputRefused, check_output, create_mode
from whiztap.analyzer.protocol.text import escape, unescape
from whiztap.sniffer.sim.channels import format_channels
from whiztap.sniffer.sim.client import Client

RAW_WAIT = 0.5  # seconds to collect whatever a raw frame brings back

HELP = """commands:
  config                     Fetch Configuration Settings
  camera [-o FILE [--force]] Fetch Camera Image (saved to FILE; --force: over an existing one)
  sensor CH                  Sensor Request
  servo CH                   Servo Position Request
  servo CH VALUE             Normal Send (move a servo to VALUE, 0-2000)
  send CH VALUE              Normal Send to any channel
  switch CH on|off           Activate / De-Activate Switch
  script N                   Play Internal (11-266) or External (270-275) Script
  script stop internal|external
  setconfig SPEC [CHECKSUM]  Set Configuration Settings, e.g. servo:0-5,sensor:6-23
  raw TEXT                   send escaped bytes (\\r, \\n, \\xNN) and show the replies
  rr1-... / sr1-...          same as raw
  sleep SECONDS              wait
  help                       this list"""


class CommandError(WhiztapError):
    """The words are not a command; the message says why."""


def _arity(words: list[str], *counts: int) -> None:
    if len(words) - 1 not in counts:
        raise CommandError(f"wrong arguments for {words[0]!r}; try 'help'")


def item_line(item: Item) -> str:
    decoded = decode(item.kind, item.raw, item.reason)
    meaning = decoded.message.describe() if decoded.message else str(item.reason or item.kind)
    return f"< {escape(item.raw) if len(item.raw) <= 80 else f'{item.kind} ({len(item.raw)} bytes)'}  {meaning}"


def split_line(line: str) -> list[str]:
    """Words of a line; a raw frame keeps its bytes (spaces, backslashes) as typed."""
    text = line.strip()
    if text.startswith(HEADERS):
        return [text]
    head, _, rest = text.partition(" ")
    if head.lower() == "raw":
        return [head, rest.strip()] if rest.strip() else [head]
    return text.split()


async def run(client: Client, words: list[str]) -> str:
    """Carry out one command; the line to print.  Raises CommandError or ClientError."""
    if not words:
        raise CommandError("no command; try 'help'")
    name = words[0].lower()
    if name.startswith(HEADERS):
        return await _raw(client, " ".join(words))
    match name:
        case "help":
            return HELP
        case "camera":  # its options are the console's; the frame is the word table's
            return await _camera(client, words)
        case _ if name in CONSOLE_WORDS:
            try:
                message = message_from_words(words)
            except FrameTextError as e:
                raise CommandError(str(e)) from None
            return await _carry_out(client, message)
        case "raw":
            if len(words) < 2:
                raise CommandError("raw needs the bytes to send")
            return await _raw(client, " ".join(words[1:]))
        case "sleep":
            _arity(words, 1)
            try:
                seconds = float(words[1])
            except ValueError:
                raise CommandError(f"sleep needs seconds, got {words[1]!r}") from None
            await asyncio.sleep(seconds)
            return f"slept {seconds:g} s"
    raise CommandError(f"unknown command {words[0]!r}; try 'help'")


async def _camera(client: Client, words: list[str]) -> str:
    rest = [w for w in words[1:] if w != "--force"]
    force = len(rest) < len(words) - 1
    if len(rest) == 2 and rest[0] in ("-o", "--output"):
        target: Path | None = Path(rest[1])
        try:  # before asking: the image is not fetched to be thrown away
            check_output(str(target), force=force)
        except OutputRefused as e:
            raise CommandError(str(e)) from None
    elif not rest and not force:
        target = None
    else:
        raise CommandError("usage: camera [-o FILE [--force]]")
    image = await client.fetch_camera_image()
    kind = "jpeg" if image.startswith(b"\xff\xd8") else "png" if image.startswith(b"\x89PNG") else "image"
    if target is None:
        return f"camera: {len(image)} bytes {kind}"
    try:
        with open(target, create_mode(str(target), force) + "b") as f:
            f.write(image)
    except FileExistsError:
        raise CommandError(f"{target} exists; use --force to overwrite it or -o to choose another name") from None
    except OSError as e:
        raise CommandError(f"cannot write {target}: {e.strerror}") from None
    return f"camera: {len(image)} bytes {kind}, saved to {target}"


async def _carry_out(client: Client, message: m.Message) -> str:
    """Send what the console's words mean (through the client, which awaits the
    answer a request asks for); the line to print."""
    match message:
        case m.FetchConfiguration():
            config = await client.fetch_configuration()
            return f"Configuration Settings: {len(config.channels)} channels: {format_channels(config.channels)}"
        case m.SensorRequest(channel=channel):
            return f"sensor {channel} = {await client.sensor(channel)}"
        case m.ServoPositionRequest(channel=channel):
            position = await client.servo_position(channel)
            return f"servo {channel} position {position:g} (data {round(position * 4)})"
        case m.SetConfiguration(entries=entries, checksum=checksum):
            await client.set_configuration(entries, checksum)
            return f"Set Configuration: {len(entries)} entries sent"
    said = _sent_line(message)
    if said is None:
        raise CommandError(f"the console cannot send {message.title}")
    await client.send(message)
    return said


def _sent_line(message: m.Message) -> str | None:
    """What the console prints for a command that awaits no answer; None for another message."""
    match message:
        case m.NormalSend(channel=channel, value=value):
            return f"Normal Send: channel {channel} -> {value}"
        case m.ActivateSwitch(channel=channel):
            return f"switch {channel} on"
        case m.DeactivateSwitch(channel=channel):
            return f"switch {channel} off"
        case m.PlayInternalScript(script=number):
            return f"play internal script {number}"
        case m.PlayExternalScript(script=number):
            return f"play external script {number}"
        case m.StopInternalScript():
            return "stop internal script"
        case m.StopExternalScript():
            return "stop external script"
    return None


async def _raw(client: Client, text: str) -> str:
    data = unescape(text)
    items = await client.exchange_raw(data, RAW_WAIT)
    lines = [f"sent {len(data)} bytes"] + [item_line(i) for i in items]
    if not items:
        lines.append(f"(no reply within {RAW_WAIT:g} s)")
    return "\n".join(lines)
