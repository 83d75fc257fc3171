"""The selected frame in full: fields with their spec ranges, violations, bytes, pairing.

Built only for the one frame under the cursor, from the store, so it may take
its time: every decoded field, each with the range the spec allows, every
violation with its rule, the exact bytes as escaped text and as hex, and the
request or response it pairs with, with the latency.
"""

from __future__ import annotations

import datetime
from collections.abc import Iterable
from typing import Any

from rich.console import Group, RenderableType
from rich.table import Table
from rich.text import Text
from textual.app import ComposeResult
from textual.containers import VerticalScroll
from textual.widgets import Static
from whiztap.analyzer.protocol.codec import (
    EXTERNAL_SCRIPTS,
    INTERNAL_SCRIPTS,
    MAX_CHANNEL,
    MAX_CONFIG_CHANNELS,
    MAX_DEVICE,
    MAX_SEND_VALUE,
    MAX_SENSOR_DATA,
    MAX_SERVO_DATA,
)
from whiztap.analyzer.protocol.describe import fields, meaning, response_meaning
from whiztap.analyzer.protocol.items import ItemKind
from whiztap.analyzer.protocol.messages import CameraImage
from whiztap.analyzer.protocol.observations import Observation
from whiztap.analyzer.protocol.rules import RULES, Violation
from whiztap.analyzer.protocol.text import escape, printable
from whiztap.analyzer.traffic import Action, Intervention
from whiztap.tui.data.controls import Controls, HeldKey
from whiztap.tui.data.marks import GLYPHS, mark_kind
from whiztap.tui.data.store import NS, FrameStore
from whiztap.tui.data.typed import TypedFrame, judge_bytes

HEX_WIDTH = 8  # bytes per hex line: fits the side pane
HEX_LINES = 128  # 1 KiB of hex; an image shows its head
MARK_BYTES = 256  # of a frame before and after an intervention
MARK_STYLES = {"held": "bold cyan", "injected": "bold green", "edited": "bold magenta", "dropped": "bold red",
               "delayed": "yellow", "faulted": "bold yellow"}
_MASKED = frozenset(b"*\r\n")  # what a masked password is made of
DROPPED = frozenset({Action.DROP, Action.BLACKHOLE})
SEVERITY_STYLE = {1: "blue", 2: "yellow", 3: "bold red"}
UNITS = {0: "servo", 1: "switch", 2: "sensor"}

# field name -> what the spec allows (Data ranges of the message descriptions)
SPEC_RANGES: dict[str, str] = {
    "channel": f"0-{MAX_CHANNEL}",
    "value": f"0-{MAX_SEND_VALUE}",
    "servo_position": f"0-{MAX_SERVO_DATA // 4} (data / 4)",
    "sensor_value": f"0-{MAX_SENSOR_DATA}",
    "checksum": "one byte, from the entries",
    "length": "any",
    "format": "jpeg or png",
    "data1": "a command code",
    "data2": "a command code",
    "data3": "0, 2, a script or stop code",
}
_SCRIPT_RANGES = {
    "Play Internal Script": f"{INTERNAL_SCRIPTS.start}-{INTERNAL_SCRIPTS.stop - 1}",
    "Play External Script": f"{EXTERNAL_SCRIPTS.start}-{EXTERNAL_SCRIPTS.stop - 1}",
}


def clock(t_ns: int) -> str:
    """UTC wall time with microseconds: recordings move between time zones."""
    t = datetime.datetime.fromtimestamp(t_ns / NS, datetime.UTC)
    return t.strftime("%Y-%m-%d %H:%M:%S.%f UTC")


def latency_text(ns: int) -> str:
    if ns < 1_000_000:
        return f"{ns / 1e3:.0f} µs"
    return f"{ns / 1e6:.2f} ms" if ns < NS else f"{ns / NS:.3f} s"


def _data_range(observation_as: str | None) -> str:
    if observation_as == "servo":
        return f"0-{MAX_SERVO_DATA} (servo data)"
    if observation_as == "sensor":
        return f"0-{MAX_SENSOR_DATA} (sensor data)"
    return f"0-{MAX_SENSOR_DATA} sensor, 0-{MAX_SERVO_DATA} servo"


def field_rows(values: dict[str, Any], answered_as: str | None) -> list[tuple[str, str, str]]:
    rows: list[tuple[str, str, str]] = []
    title = values.get("message", "")
    for name, value in values.items():
        if name in ("message", "latency_ns", "candidates"):
            continue
        if name == "channels":  # Configuration Settings: one row per channel
            rows.append(("channels", str(len(value)), f"at most {MAX_CONFIG_CHANNELS}"))
            for ch, c in enumerate(value):
                unit = UNITS.get(c["unit_type"], f"? {c['unit_type']}")
                rows.append((f"  ch {ch}", f"{unit} (unused {c['unused']}, switch type {c['switch_type']})",
                             "unit 0-2, unused 0, switch type 0-1"))
        elif name == "entries":  # Set Configuration: one row per entry
            for i, e in enumerate(value):
                unit = UNITS.get(e["unit_type"], f"? {e['unit_type']}")
                rows.append((f"  entry {i}", f"dev {e['device']} port {e['port']} {unit}",
                             f"dev 0-{MAX_DEVICE}, port 0-{MAX_CHANNEL}, unit 0-2"))
        elif name == "data" and title == CameraImage.title:  # its size; the spec sets no limit
            rows.append(("size", f"{value:,} bytes", "any (whiztap takes up to --max-image)"))
        elif name == "data":
            rows.append((name, str(value), _data_range(answered_as) if isinstance(value, int) else "bytes"))
        elif name == "script":
            rows.append((name, str(value), _SCRIPT_RANGES.get(title, "")))
        else:
            rows.append((name, str(value), SPEC_RANGES.get(name, "")))
    return rows


def hex_dump(data: bytes, lines: int = HEX_LINES, width: int = HEX_WIDTH) -> str:
    out = []
    for offset in range(0, min(len(data), lines * width), width):
        chunk = data[offset:offset + width]
        hexes = " ".join(f"{b:02x}" for b in chunk)
        text = "".join(chr(b) if 0x20 <= b < 0x7F else "." for b in chunk)
        out.append(f"{offset:04x}  {hexes:<{3 * width - 1}}  {text}")
    return "\n".join(out)


def describe_frame(store: FrameStore, n: int) -> RenderableType:
    """Everything about frame ``n`` as one renderable: Text and plain cells,
    never markup (a detail may quote the wire), control characters escaped."""
    with store.lock:
        obs = store.observation(n)
        values = store.fields(n)
        meaning = store.meaning(n)
        size = store.size(n)
        paired = store.pair[n]
        paired_meaning = store.meaning(paired) if paired >= 0 else ""
        paired_latency = abs(store.t_end[n] - store.t_end[paired]) if paired >= 0 else 0
        clients = client_latency(store, n, paired) if paired >= 0 else None
        conn = store.conn[n]
        ordinal = store.conn_ordinal(n)
        relative = store.relative_s(n)
        marks = list(store.marks.get(n, ()))
        secret = store.redact_passwords and obs.item.kind is ItemKind.PASSWORD
    parts: list[RenderableType] = [_heading(obs, meaning, conn, ordinal, relative)]
    if obs.message is None and obs.candidates:
        parts.append(Text(printable("may mean: " + " / ".join(c.describe() for c in obs.candidates)),
                          style="yellow"))
    rows = field_rows(values, response_meaning(obs))
    if rows:
        parts.append(fields_table(rows))
    if obs.violations:
        parts.append(violations_text(obs.violations))
    if marks:
        parts.append(marks_text(marks, secret))
    if paired >= 0:
        pairing = Text("Pairing\n", style="bold")
        what = "answers" if obs.direction.sender == "server" else "answered by"
        pairing.append(f"{what}: {printable(paired_meaning)}\n")
        if clients is None:
            pairing.append(f"latency {latency_text(paired_latency)}  (p jumps there)")
        else:  # the proxy changed the timing: each side waited its own time
            pairing.append(f"latency for the server {latency_text(paired_latency)}, "
                           f"for the client {clients}  (p jumps there)")
        parts.append(pairing)
    parts += _bytes_parts(store.raw(n), size)
    return Group(*parts)


def client_latency(store: FrameStore, n: int, paired: int) -> str | None:
    """In the middle, the client's latency for the pair of ``n`` and
    ``paired`` when the proxy changed their timing (None: it did not, and the
    client waited as the server did): from when the client sent the request
    to when it got the answer (``FrameStore.client_t``)."""
    request, answer = (paired, n) if paired < n else (n, paired)
    times = store.client_t
    if any(m.action in DROPPED for m in store.marks.get(answer, ())):
        return "never: the proxy dropped the answer"
    if any(m.action is Action.INJECT for m in store.marks.get(request, ())):
        return "none: the proxy injected the request"
    if request not in times and answer not in times:
        return None
    return latency_text(times.get(answer, store.t_end[answer]) - times.get(request, store.t_end[request]))


def _heading(obs: Observation, meaning: str, conn: int, ordinal: int, relative: float) -> Text:
    """What the frame means, where it belongs and when it came.  ``ordinal``:
    its place among the connection's rows, counted as the connections pane
    and the list (with the connection chosen) count them."""
    item = obs.item
    head = Text()
    head.append(printable(meaning), style="bold")
    head.append("\n" + printable(f"frame {ordinal:,} of conn #{conn}, {obs.direction.sender} → "
                                 f"{'server' if obs.direction.sender == 'client' else 'client'}, {item.kind}"
                                 + (f" ({item.reason})" if item.reason else "")), style="dim")
    head.append(f"\nat {relative:.6f} s  ({clock(item.t_end_ns)})", style="dim")
    if item.t_start_ns != item.t_end_ns:
        head.append(f"\nfirst byte {(item.t_end_ns - item.t_start_ns) / 1e6:.3f} ms earlier", style="dim")
    return head


def fields_table(rows: list[tuple[str, str, str]]) -> Table:
    table = Table(title="Fields", title_justify="left", expand=True, show_edge=False, pad_edge=False)
    table.add_column("field", style="cyan", no_wrap=True)
    table.add_column("value")
    table.add_column("spec allows", style="dim")
    for row in rows:
        table.add_row(*(Text(printable(cell)) for cell in row))
    return table


def violations_text(found: Iterable[Violation]) -> Text:
    violations = Text("Violations\n", style="bold")
    for v in found:
        rule = RULES[v.rule_id]
        violations.append(f"● {v.rule_id}", style=SEVERITY_STYLE[rule.severity])
        violations.append(f" ({rule.severity}, {v.section})\n", style="dim")  # the message's section
        violations.append(f"  {rule.summary}\n  {printable(v.detail)}\n")
    return violations


def marks_text(marks: list[Intervention], secret: bool = False) -> Text:
    """What the proxy in the middle did to the frame, each thing on its own:
    the kind (as the list's glyph), the action and its cause, the frame before
    and after as escaped text, and how (a delay's length, a hold's number).
    ``secret``: the frame is a password shown masked; a mark on a frame that
    may be one says ``<redacted>`` too."""
    text = Text("What the proxy did\n", style="bold")
    for mark in marks:
        kind = mark_kind(mark)
        text.append(f"{GLYPHS[kind]} {mark.action}", style=MARK_STYLES[kind])
        text.append(f"  {printable(str(mark.cause))}" + (f" (held #{mark.held})" if mark.held else "") + "\n")
        hidden = secret or (mark.secret and set(mark.before + mark.after) <= _MASKED)
        for label, data in (("before", mark.before), ("after", mark.after)):
            shown = "<redacted>" if hidden and data else escape(data[:MARK_BYTES]) if data else "(nothing)"
            text.append(f"  {label:<7}", style="dim")
            text.append(shown + ("…" if len(data) > MARK_BYTES and not hidden else "") + "\n")
        if mark.detail:
            text.append(f"  {printable(mark.detail)}\n", style="dim")
    return text


def describe_typed(typed: TypedFrame) -> RenderableType:
    """A typed frame as the dialogs show it beside the text: what it means,
    its bytes and fields, and the rules it breaks (or that it breaks none)."""
    if typed.data is None:
        hint = "type a frame: escaped text (rr1-12--0--0-ss1) or console words (sensor 12, servo 3 1500)"
        return Text(printable(typed.error or hint), style="bold red" if typed.error else "dim")
    parts: list[RenderableType] = []
    obs = typed.observation
    if obs is not None:
        parts.append(Text(printable(meaning(obs)), style="bold"))
    shown = Text(f"{len(typed.data)} bytes: ", style="dim")
    shown.append(escape(typed.data[:1024]) + ("…" if len(typed.data) > 1024 else ""), style="bold")
    parts.append(shown)
    rows = field_rows(fields(obs), None) if obs is not None else []
    if rows:
        parts.append(fields_table(rows))
    if typed.error:
        parts.append(Text(printable(typed.error), style="bold red"))
    elif typed.violations:
        parts.append(violations_text(typed.violations))
    else:
        parts.append(Text("Breaks no rule (judged alone: the handshake, the channel map and the pairing "
                          "need the session)", style="green"))
    return Group(*parts)


def describe_held(held: Any, controls: Controls) -> RenderableType:
    """A frame the proxy holds (a ``Held``): where it goes, why it waits and
    for how much longer, the keys that let it go, and the frame as the
    editor would judge it."""
    state = held.as_dict(controls.now_ns)
    sender = held.direction.sender
    waited, left = controls.waits(held)
    head = Text(f"Held #{held.id}, waiting {waited} s; goes on as it is in {left} s (--hold-timeout)",
                style="bold cyan")
    head.append("\n" + printable(f"conn #{held.conn}, {sender} → {'server' if sender == 'client' else 'client'}, "
                                  f"{state['kind']}; {state['cause']}"), style="dim")
    head.append("\na accept · x drop · e edit · A accept all", style="bold")
    return Group(head, describe_typed(judge_bytes(held.shown, held.direction, controls.checksum_rule)))


def _bytes_parts(kept: bytes, size: int) -> list[RenderableType]:
    """The kept bytes, escaped, then as a hex dump."""
    shown = Text("Bytes", style="bold")
    shown.append(f" ({size} bytes" + (f", first {len(kept)} kept" if len(kept) < size else "") + ")\n")
    shown.append(escape(kept[:1024]) + ("…" if len(kept) > 1024 else ""), style="bold")
    dump = hex_dump(kept)
    more = len(kept) - HEX_LINES * HEX_WIDTH
    return [shown, Text(dump + (f"\n… {more} more bytes" if more > 0 else ""), style="dim")]


class DetailPane(VerticalScroll):
    """Shows one frame; empty until the cursor is on one."""

    DEFAULT_CSS = """
    DetailPane { padding: 0 1; }
    DetailPane > Static { width: 100%; }
    """

    def __init__(self, store: FrameStore, controls: Controls | None = None, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.store = store
        self.controls = controls
        self.frame: int | HeldKey | None = None
        self.body = Static("No frame yet.", id="detail-body")  # made here: updates never wait on a query

    def compose(self) -> ComposeResult:
        yield self.body

    def show(self, frame: int | HeldKey | None) -> None:
        """Show a stored frame, or a frame the proxy holds (the list's rows after its own)."""
        if frame == self.frame:
            return
        self.frame = frame
        self.body.update(self._describe(frame))
        self.scroll_home(animate=False)

    def _describe(self, frame: int | HeldKey | None) -> RenderableType:
        if frame is None:
            return "No frame yet."
        if not isinstance(frame, HeldKey):
            return describe_frame(self.store, frame)
        controls = self.controls
        held = controls.find(frame.id) if controls is not None else None
        if held is None or controls is None:
            return Text(f"Held #{frame.id} has been let go.")
        return describe_held(held, controls)

    def refresh_frame(self) -> None:
        """Show the frame again: a late violation may have marked it."""
        frame, self.frame = self.frame, None
        self.show(frame)
