"""One frame on its way through the proxy's stages, and what they decided.

Every stage (the faults, the scripts, the person intercepting) sees the same
``Frame``: what the sender sent, judged alone as every frame on its own is
(``item_alone``, analyzer/protocol/frame_text.py: the proxy judges frames one
by one, not as a session), and what is to be delivered so far.
A stage changes the delivery through the methods here, each of which also
notes an ``Intervention`` (the recording's account of every change: what
changed it, the frame before and after, as facts).  The middle's core
(``core.py``) then carries out the final decision, in order.

A frame that is (or may be) a password is ``secret``: unless the run keeps
secrets, its interventions carry its bytes masked, so no output of the
middle (the file, the API, the TUI, Foxglove, a script's log line) can show it.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field

from whiztap.analyzer.protocol.framing import Item, ItemKind
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.traffic import Action, Cause, Intervention

MS = 1_000_000
_MASKABLE = re.compile(rb"[^\r\n]")


def masked(data: bytes) -> bytes:
    """A password's bytes as every output shows them: ``*`` but CR and LF, the length kept."""
    return _MASKABLE.sub(b"*", data)


@dataclass
class Frame:
    """A framer item of one direction of connection ``conn``, and its fate.

    ``index`` is its number among its sender's frames in that direction,
    ``offset`` where it begins in its sender's stream;
    ``data`` is what will be delivered (``None``: nothing, it was dropped);
    ``copies`` how many times; ``delay_ns`` how much later than now;
    ``slices``/``pause_ns`` in writes of how many bytes, how far apart;
    ``hold`` whether a person must let it go first; ``end`` a connection action
    (reset or close) carried out after the frame; ``injections`` other frames
    sent once it is decided.  ``secret``/``redact``: the frame may be a
    password, and the run hides passwords."""

    conn: int
    direction: Direction
    item: Item
    observation: Observation
    t_ns: int
    opened_ns: int = 0  # when its connection opened (faults' clocks start there)
    index: int = -1
    offset: int = -1  # where it begins in its sender's stream
    secret: bool = False
    redact: bool = True
    data: bytes | None = None
    copies: int = 1
    delay_ns: int = 0
    slices: tuple[int, int] | None = None
    pause_ns: int = MS
    hold: str | None = None  # the intercept filter that holds it, or None
    end: Action | None = None
    # frames to send after this one: (direction, bytes, cause); a tuple, so a failed stage's are undone with it
    injections: tuple[tuple[Direction, bytes, Cause], ...] = ()
    interventions: list[Intervention] = field(default_factory=list)

    def __post_init__(self) -> None:
        if self.data is None:
            self.data = self.item.raw

    def state(self) -> tuple:
        """What a stage may change, to put back if the stage fails (``restore``)."""
        return (self.data, self.copies, self.delay_ns, self.slices, self.pause_ns, self.hold, self.end,
                self.injections)

    def restore(self, state: tuple) -> None:
        (self.data, self.copies, self.delay_ns, self.slices, self.pause_ns, self.hold, self.end,
         self.injections) = state

    @property
    def kind(self) -> ItemKind:
        return self.item.kind

    @property
    def raw(self) -> bytes:
        """The bytes the sender sent."""
        return self.item.raw

    @property
    def hidden(self) -> bool:
        """Its bytes are shown masked (a password in a run that hides them)."""
        return self.secret and self.redact

    @property
    def dropped(self) -> bool:
        return self.data is None

    def note(self, action: Action, cause: Cause, before: bytes | None, after: bytes | None, detail: str = "") -> None:
        """Record a change (``None`` bytes are recorded as empty)."""
        before, after = before or b"", after or b""
        if self.hidden:
            before, after = masked(before), masked(after)
        self.interventions.append(Intervention(self.conn, self.t_ns, self.direction, action, cause, before, after,
                                               self.item.kind.value, detail, self.index, 0, self.secret,
                                               self.offset))

    # -- what a stage may do --------------------------------------------------------------

    def drop(self, cause: Cause, action: Action = Action.DROP) -> None:
        if self.data is not None:
            self.note(action, cause, self.data, None)
            self.data = None

    def replace(self, data: bytes, cause: Cause, action: Action = Action.REPLACE) -> None:
        if self.data is not None and data != self.data:
            self.note(action, cause, self.data, data)
            self.data = data

    def duplicate(self, cause: Cause) -> None:
        if self.data is not None:
            self.copies += 1
            self.note(Action.DUP, cause, self.data, self.data, f"delivered {self.copies} times")

    def delay(self, delay_ns: int, cause: Cause) -> None:
        if self.data is not None and delay_ns > 0:
            self.delay_ns += delay_ns
            self.note(Action.DELAY, cause, self.data, self.data, f"delayed {delay_ns / MS:g} ms")

    def slice(self, smallest: int, largest: int, pause_ns: int, cause: Cause, action: Action = Action.SLICE) -> None:
        if self.data is not None:
            self.slices, self.pause_ns = (smallest, largest), pause_ns
            size = str(smallest) if smallest == largest else f"{smallest}-{largest}"
            self.note(action, cause, self.data, self.data, f"in writes of {size} bytes, {pause_ns / MS:g} ms apart")

    def inject(self, direction: Direction, data: bytes, cause: Cause) -> None:
        """Send ``data`` toward the receiver of ``direction`` once this frame
        is decided: in this frame's direction it goes right behind the frame
        (and waits as long as the frame does); the core notes the injection."""
        self.injections += ((direction, data, cause),)

    def end_connection(self, how: Action, cause: Cause, instead: bool = False) -> None:
        """``how``: RESET (both sides get a TCP reset now) or CLOSE (both get a
        normal close once what is before it is delivered); ``instead``: in
        place of the frame, which is then not delivered (one intervention says both)."""
        if self.end is None:
            self.end = how
            after = None if instead else self.data
            self.note(how, cause, self.data, after, f"the proxy {how}s the connection"
                      + (" instead of delivering the frame" if instead else ""))
            if instead:
                self.data = None

