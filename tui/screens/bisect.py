"""Bisect (``b``): where did it start?  The first frame breaking a rule, or the
first frame where two connections part.

The prompt takes one of:

- a rule id (``PW-PAIR-UNANSWERED``), a family of rules (``PW-PAIR``: every
  rule whose id starts ``PW-PAIR-``) or a severity (``error``, ``warning``,
  ``info``): the list moves to the first frame in view (in arrival order,
  under the current filter) with a violation of it.  There is no binary
  search: the store keeps the ids of frames with violations in order
  (``FrameStore.violating``), so the first match is a walk from the start of
  that list.  "Bisect" names the question, as git's does, not the method.
- two connection numbers ``A B`` (say a session and a replay of it, both in
  one recording: the TUI's live proxy with the client, then ``whiztap
  replay`` through it): each connection's client frames are compared with
  the other's client frames in order, and server frames with server frames,
  by kind and bytes; the first pair that differs (or a frame the other side
  does not have) is shown side by side with a few frames around it, and
  Escape returns to the list on connection A's frame there.  The whole
  connections are compared, whatever the filter (a filter hiding one side
  would make everything differ).

Both searches read the store from a worker thread: a million frames take a
moment, and the screen stays live meanwhile.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from rich.text import Text
from textual import on, work
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Vertical, VerticalScroll
from textual.screen import ModalScreen
from textual.widgets import Input, Static
from textual.worker import Worker, WorkerState, get_current_worker
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.rules import RULES, Severity, Violation
from whiztap.analyzer.protocol.text import escape, printable
from whiztap.tui.data.store import FrameStore
from whiztap.tui.data.view import FrameView

if TYPE_CHECKING:
    from whiztap.tui.widgets.frame_list import FrameList

CONTEXT = 4  # frames shown before and after the first difference
SIDE_WIDTH = 56  # characters for each connection's side of a row
DETAIL_BYTES = 160  # escaped characters of each differing frame shown in full below the rows
SEVERITIES = {str(s): s for s in Severity}
_TWO_CONNECTIONS = re.compile(r"#?(\d+)[\s,]+#?(\d+)")
PROMPT = ("Bisect to the first frame with a violation of a rule (PW-PAIR-UNANSWERED), a family (PW-PAIR) "
          "or a severity (error, warning, info); or to where two connections first differ (1 2).")
HINT = "type a rule id (whiztap rules lists them), error, warning or info, or two connection numbers"

Key = tuple[bool, int]  # (server to client, index among the connection's frames that way)


class BisectError(WhiztapError, ValueError):
    """The query does not read, or finds nothing (one line, shown in the prompt)."""


@dataclass(frozen=True)
class RuleQuery:
    """Frames with a violation of one of ``rules``, or of ``severity``."""

    text: str  # as the prompt says it back
    rules: frozenset[str] = frozenset()
    severity: Severity | None = None

    def matches(self, violations: tuple[Violation, ...]) -> bool:
        if self.severity is not None:
            return any(v.severity == self.severity for v in violations)
        return any(v.rule_id in self.rules for v in violations)


@dataclass(frozen=True)
class ConnectionPair:
    """Connection ``a`` (whose frame the list returns to) and connection ``b``."""

    a: int
    b: int


@dataclass(frozen=True)
class Row:
    """Frames of the two connections at the same place (None: that side has none there)."""

    a: int | None
    b: int | None
    differs: bool


@dataclass(frozen=True)
class Divergence:
    """The first difference between two connections, with CONTEXT rows either side."""

    pair: ConnectionPair
    rows: tuple[Row, ...]
    first: int  # the first difference's index in rows
    key: Key  # its direction and place among that direction's frames
    counts: tuple[int, int]  # frames of a, of b

    @property
    def row(self) -> Row:
        return self.rows[self.first]


def parse_query(text: str) -> RuleQuery | ConnectionPair:
    """What the prompt asks for; BisectError (one line) for what does not read."""
    words = text.strip()
    if not words:
        raise BisectError(HINT)
    two = _TWO_CONNECTIONS.fullmatch(words)
    if two:
        a, b = int(two[1]), int(two[2])
        if a == b:
            raise BisectError(f"#{a} twice: give two different connections")
        return ConnectionPair(a, b)
    severity = SEVERITIES.get(words.lower())
    if severity is not None:
        return RuleQuery(str(severity), severity=severity)
    rule = words.upper()
    family = frozenset(r for r in RULES if r == rule or r.startswith(rule + "-"))
    if not family:
        raise BisectError(f"unknown rule {printable(words)!r}: {HINT}")
    return RuleQuery(rule, rules=family)


# -- the searches (worker threads) -----------------------------------------------------------------


def first_violation(store: FrameStore, view: FrameView, query: RuleQuery,
                    cancelled: Callable[[], bool]) -> int | None:
    """The first frame in ``view`` with a violation ``query`` matches."""
    for n in store.violations_from(0, 1):
        if cancelled():
            return None
        if query.matches(store.violations.get(n, ())):
            row = view.row_of(n)
            if row < len(view) and view[row] == n:
                return n
    return None


def diverge(store: FrameStore, pair: ConnectionPair, cancelled: Callable[[], bool]) -> Divergence | None:
    """Where the two connections first differ; None when they carry the same
    frames (or when cancelled); BisectError for a connection without frames."""
    frames = _frames_of(store, pair)
    for conn, found in zip((pair.a, pair.b), frames):
        if not found:
            raise BisectError(f"connection #{conn} has no frame here")
    rows = _aligned(store, *frames)
    for i, (key, a, b) in enumerate(rows):
        if cancelled():
            return None
        if not _same(store, a, b):
            start = max(0, i - CONTEXT)
            window = tuple(Row(x, y, not _same(store, x, y)) for _, x, y in rows[start:i + CONTEXT + 1])
            return Divergence(pair, window, i - start, key, (len(frames[0]), len(frames[1])))
    return None


def _frames_of(store: FrameStore, pair: ConnectionPair) -> tuple[list[int], list[int]]:
    """Each connection's frame ids, in arrival order."""
    with store.lock:
        conns = store.conn[:store.count]
    a: list[int] = []
    b: list[int] = []
    for n, conn in enumerate(conns):
        if conn == pair.a:
            a.append(n)
        elif conn == pair.b:
            b.append(n)
    return a, b


def _keys(store: FrameStore, frames: list[int]) -> list[Key]:
    """Each frame's direction and place among its connection's frames that way."""
    counts = [0, 0]
    keys = []
    for n in frames:
        s2c = store.direction(n) is Direction.S2C
        keys.append((s2c, counts[s2c]))
        counts[s2c] += 1
    return keys


def _aligned(store: FrameStore, a_frames: list[int], b_frames: list[int]) -> list[tuple[Key, int | None, int | None]]:
    """Rows pairing each of A's frames with B's frame of the same key, in A's
    order; B's frames beyond A's (in their direction) follow the row of B's
    frame before them, so a side that goes on shows where it went on."""
    a_keys, b_keys = _keys(store, a_frames), _keys(store, b_frames)
    b_by_key = dict(zip(b_keys, b_frames))
    a_at = {key: i for i, key in enumerate(a_keys)}
    ordered: list[tuple[tuple[int, int, int], Key, int | None, int | None]] = [
        ((i, 0, 0), key, a, b_by_key.get(key)) for i, (key, a) in enumerate(zip(a_keys, a_frames))]
    last = -1
    for j, (key, b) in enumerate(zip(b_keys, b_frames)):
        i = a_at.get(key)
        if i is None:
            ordered.append(((last, 1, j), key, None, b))
        else:
            last = i
    ordered.sort(key=lambda row: row[0])
    return [(key, a, b) for _, key, a, b in ordered]


def _same(store: FrameStore, a: int | None, b: int | None) -> bool:
    return a is not None and b is not None and store.kind(a) is store.kind(b) \
        and store.size(a) == store.size(b) and store.raw(a) == store.raw(b)


# -- what the screens show ---------------------------------------------------------------------------


def _side(store: FrameStore, n: int | None) -> str:
    if n is None:
        return f"{'(no frame)':<{SIDE_WIDTH}}"
    arrow = "←" if store.direction(n) is Direction.S2C else "→"
    line = f"{store.relative_s(n):10.6f} {arrow} {store.kind(n):<10} {escape(store.raw(n))}"
    return f"{line:<{SIDE_WIDTH}}" if len(line) <= SIDE_WIDTH else line[:SIDE_WIDTH - 1] + "…"


def divergence_text(store: FrameStore, d: Divergence) -> Text:
    """The rows side by side, the first difference marked ▶ and each other
    difference ≠, then the two differing frames in full."""
    a, b = d.pair.a, d.pair.b
    s2c, index = d.key
    text = Text()
    text.append(f"Connections #{a} ({d.counts[0]} frames) and #{b} ({d.counts[1]} frames) first differ "
                f"at {'server' if s2c else 'client'} frame {index + 1}\n\n", style="bold")
    text.append(f"  {'#' + str(a):<{SIDE_WIDTH}} │ #{b}\n", style="bold")
    for i, row in enumerate(d.rows):
        mark = "▶ " if i == d.first else "≠ " if row.differs else "  "
        style = "bold reverse red" if i == d.first else "red" if row.differs else ""
        text.append(f"{mark}{_side(store, row.a)} │ {_side(store, row.b)}\n", style=style)
    text.append("\n")
    for conn, n in ((a, d.row.a), (b, d.row.b)):
        if n is None:
            text.append(f"#{conn}: no frame here\n")
            continue
        raw = escape(store.raw(n))
        raw = raw if len(raw) <= DETAIL_BYTES else raw[:DETAIL_BYTES - 1] + "…"
        text.append(f"#{conn}: {raw}\n    {printable(store.meaning(n))}\n")
    text.rstrip()
    return text


class BisectPrompt(ModalScreen[int | Divergence | None]):
    """Asks what to bisect to; searches in a worker; says in place what went wrong."""

    BINDINGS = [Binding("escape", "dismiss(None)", "Cancel")]
    DEFAULT_CSS = """
    BisectPrompt { align: center middle; }
    BisectPrompt > Vertical {
        width: 90; max-width: 100%; height: auto;
        border: thick $primary; background: $surface; padding: 0 1;
    }
    BisectPrompt #bisect-said { color: $error; }
    BisectPrompt #bisect-said.busy { color: $text-muted; }
    """

    def __init__(self, store: FrameStore, view: FrameView, prefill: str, settled: bool) -> None:
        super().__init__()
        self.store = store
        self.view = view
        self.prefill = prefill
        self.settled = settled  # every frame loaded and judged by the filter
        self.said = Static("", id="bisect-said")

    def compose(self) -> ComposeResult:
        with Vertical():
            yield Static(PROMPT)
            yield Input(self.prefill, placeholder="PW-PAIR-UNANSWERED, error, or 1 2", id="bisect-query")
            yield self.said

    def _say(self, line: str, busy: bool = False) -> None:
        said = self.said
        said.set_class(busy, "busy")
        said.update(Text(line))  # quotes what was typed: never markup

    @on(Input.Submitted, "#bisect-query")
    def _on_submitted(self, message: Input.Submitted) -> None:
        try:
            query = parse_query(message.value)
        except BisectError as e:
            self._say(str(e))
            return
        self._say("searching…", busy=True)
        self._search(query)

    @work(thread=True, exclusive=True, group="bisect", exit_on_error=False)
    def _search(self, query: RuleQuery | ConnectionPair) -> int | Divergence:
        worker = get_current_worker()
        if isinstance(query, RuleQuery):
            found = first_violation(self.store, self.view, query, lambda: worker.is_cancelled)
            if found is None:
                raise BisectError(f"no frame in view has a violation of {query.text}"
                                  + ("" if self.settled else " yet"))
            return found
        divergence = diverge(self.store, query, lambda: worker.is_cancelled)
        if divergence is None:
            raise BisectError(f"connections #{query.a} and #{query.b} carry the same frames")
        return divergence

    @on(Worker.StateChanged)
    def _on_searched(self, event: Worker.StateChanged) -> None:
        if event.state is WorkerState.SUCCESS:
            self.dismiss(event.worker.result)
        elif event.state is WorkerState.ERROR:
            error = event.worker.error
            self._say(str(error) if isinstance(error, BisectError) else f"the search failed: {error!r}")


class DivergenceScreen(ModalScreen[int | None]):
    """Two connections side by side around their first difference; Escape
    returns to the list on connection A's frame there (B's, if A has none)."""

    BINDINGS = [Binding("escape", "back", "Back to the list")]
    DEFAULT_CSS = """
    DivergenceScreen { align: center middle; }
    DivergenceScreen > VerticalScroll {
        width: auto; max-width: 100%; height: auto; max-height: 100%;
        border: thick $primary; background: $surface; padding: 0 1;
    }
    DivergenceScreen #divergence { width: auto; }
    """

    def __init__(self, store: FrameStore, divergence: Divergence) -> None:
        super().__init__()
        self.store = store
        self.divergence = divergence

    def compose(self) -> ComposeResult:
        with VerticalScroll() as box:
            box.border_title = "Bisect: where the connections part"
            box.border_subtitle = "Esc: back to the list"
            yield Static(divergence_text(self.store, self.divergence), id="divergence")

    def action_back(self) -> None:
        row = self.divergence.row
        self.dismiss(row.a if row.a is not None else row.b)


def open_bisect(app: App, store: FrameStore, frames: FrameList, fed: bool) -> None:
    """The prompt, pre-filled with the rule of the selected frame's first
    violation; then the list's jump, or the side-by-side screen and the jump.
    ``fed``: the traffic is all in (the app's source ended)."""
    selected = frames.frame
    violations = store.violations.get(selected, ()) if selected is not None else ()
    settled = fed and frames.view.complete

    def jump(frame: int | None) -> None:
        if frame is None:
            return
        frames.focus()
        if not frames._jump(frame):  # the list's own jump, as n and p use it
            app.notify("that frame is hidden by the filter", severity="warning", timeout=4)

    def found(result: int | Divergence | None) -> None:
        if isinstance(result, Divergence):
            app.push_screen(DivergenceScreen(store, result), jump)
        else:
            jump(result)

    prompt = BisectPrompt(store, frames.view, violations[0].rule_id if violations else "", settled)
    app.push_screen(prompt, found)
