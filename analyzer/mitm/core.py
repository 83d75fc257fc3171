"""One connection with the proxy in the middle, sans-IO: events in, commands out.

``MiddleCore`` is the whole of what the proxy in the middle decides for one
connection, in the manner of h11 and wsproto: it takes events (bytes a side
sent and when, a side's FIN, the receiver being there, a side gone, a timer,
a control command: inject, release, edit, drop, a fault added) and answers
each with commands (``commands.py``: deliver bytes to a side, pass a FIN on,
end the connection, tell the consumers a traffic event, wake me at T).  It has
no socket, no event loop and no clock: every call brings the time, so every
fault (delay, bandwidth, slice, after:, for:, a hold's timeout) runs the same
on a test's fake clock as on the proxy's.

It follows the handshake as the session model does (a password is framed only
once the server asks for it), and keeps the password rule for everything it
emits: what the server received is told as ``Delivered`` events split by the
recorder's own rule (``LoginMask`` over the bytes the server received and
sent), and every frame the client sent that may be its password is
``secret``, so its interventions and held rows carry it masked unless the run
keeps secrets.
"""

from __future__ import annotations

import random
import re
from collections import deque
from dataclasses import dataclass, field, replace

from whiztap.analyzer.mitm.commands import Closing, Command, Deliver, EndConnection, Full, PassEof, Tell, WakeAt
from whiztap.analyzer.mitm.faults import Fault
from whiztap.analyzer.mitm.frame import Frame, masked
from whiztap.analyzer.mitm.intercept import Held, HeldFrames
from whiztap.analyzer.mitm.lane import Lane, Notes, Out, Segments
from whiztap.analyzer.mitm.stages import Stages
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.protocol.frame_text import item_alone
from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.handshake import SENDCHKPASS, VERDICTS
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.recording.redaction import HOLD_LIMIT_S, LoginMask
from whiztap.analyzer.traffic import Action, Cause, Data, Delivered, Intervention, Source

C2S, S2C = Direction.C2S, Direction.S2C
OTHER = {C2S: S2C, S2C: C2S}
_LOGIN_HOLD_NS = int(HOLD_LIMIT_S * 1e9)
_MASKABLE = re.compile(rb"[^\r\n]+")
CLOSING = Cause(Source.CLOSING)


@dataclass
class MiddleContext:
    """What every connection's core shares (the ``Controller`` owns it): the
    stages, the faults in force, the held frames, chance, the framer's limits,
    the checksum rule a frame is judged by, whether passwords are hidden, and
    how long a frame may stay held."""

    stages: Stages
    held: HeldFrames = field(default_factory=HeldFrames)
    faults: list[Fault] = field(default_factory=list)
    rng: random.Random = field(default_factory=random.Random)
    limits: Limits = field(default_factory=Limits)
    checksum_rule: str = DEFAULT_CHECKSUM_RULE
    redact: bool = True
    hold_timeout_ns: int = 60_000_000_000

    def __post_init__(self) -> None:
        get_rule(self.checksum_rule)  # an unknown rule fails here (ValueError), not at the first frame


class MiddleCore:
    def __init__(self, conn: int, opened_ns: int, context: MiddleContext) -> None:
        self.conn = conn
        self.opened_ns = opened_ns
        self.context = context
        limits = context.limits
        self.lanes = {d: Lane(self, d, Framer(limits.max_frame, limits.max_image)) for d in (C2S, S2C)}
        self.gone = False  # nothing more is written (both sides gone, or reset)
        self.closing = False  # a side is gone: no control command is taken
        self.sent = LoginMask()  # the recorder's rule over what the client sent: which of its bytes are the password
        self._undecided: deque[tuple[Segments, bytes, int]] = deque()  # deliveries to the server not yet told
        self._undecided_since: int | None = None
        self._timed: list[tuple[int, Fault]] = []  # (when, fault): a reset or close after a time
        self._holds: dict[int, tuple[Lane, Out, Held]] = {}
        self._delivered = {C2S: 0, S2C: 0}  # bytes delivered toward each receiver: /tcp/delivered offsets
        self._commands: list[Command] = []
        self._wake: int | None = None

    # -- events in -------------------------------------------------------------------------------

    def received(self, direction: Direction, data: bytes, t_ns: int) -> list[Command]:
        """``data`` came from the sender of ``direction`` at ``t_ns``: told as
        the read it is (``Data``), after the delivered client bytes that what
        the server says decides, so every consumer sees them in that order."""
        if direction is S2C:  # what the server says may decide the delivered client bytes told before
            self.sent.server(data)
            self._tell_decided()
        else:
            self.sent.client(data)
        self._commands.append(Tell(Data(self.conn, direction, t_ns, data)))
        self.lanes[direction].feed(data, t_ns)
        return self._done(t_ns)

    def ready(self, direction: Direction, t_ns: int) -> list[Command]:
        """The receiver of ``direction`` is there (the server once connected)."""
        lane = self.lanes[direction]
        lane.ready = True
        lane.pump(t_ns)
        return self._done(t_ns)

    def writable(self, direction: Direction, t_ns: int) -> list[Command]:
        """The receiver of ``direction`` takes more: its lane writes on (it stops after a burst)."""
        self.lanes[direction].writable(t_ns)
        return self._done(t_ns)

    def blocked(self, direction: Direction) -> bool:
        """The lane of ``direction`` waits for its receiver to take more (``writable``)."""
        return self.lanes[direction].blocked

    def sender_ended(self, direction: Direction, t_ns: int) -> list[Command]:
        """The sender of ``direction`` sent its FIN: the FIN follows what its lane holds."""
        if direction is S2C:  # the server will say nothing more about a login
            self.sent.server_ended()
            self._tell_decided()
        self.lanes[direction].end(t_ns)
        return self._done(t_ns)

    def lost(self, sender: Direction, t_ns: int) -> list[Command]:
        """The socket that sends ``sender`` is gone (reset or closed): what it
        sent goes to the other side now, held frames as they are; nothing can
        reach it any more, so what waits for it expires.  Control commands
        are refused from here on."""
        if self.closing:
            return self._done(t_ns)
        self.closing = True
        self._release_holds(t_ns, (sender,))
        gone = self.lanes[OTHER[sender]]
        gone.drop_all(t_ns)
        gone.ready = False  # what its sender still sends waits, and expires at the close
        self.lanes[sender].flush(t_ns)
        self.sent.end()  # undecided client bytes are masked
        self._tell_decided()
        return self._done(t_ns)

    def closed(self, t_ns: int) -> list[Command]:
        """Both sides are gone: whatever still waits expires, and nothing more wakes."""
        self.closing = True
        for lane in self.lanes.values():
            lane.drop_all(t_ns)
        self.gone = True
        self.sent.end()
        self._tell_decided()
        self._timed.clear()
        return self._done(t_ns)

    def wake(self, t_ns: int) -> list[Command]:
        """A timer fired: whatever is due at ``t_ns`` happens.  The timer is
        spent, so the next wake-up is asked for again (also when a timer fired
        a little early and nothing was due yet)."""
        self._wake = None
        due = [fault for at, fault in self._timed if at <= t_ns]
        self._timed = [(at, fault) for at, fault in self._timed if at > t_ns]
        for fault in due:
            self._timed_end(fault, t_ns)
        if self._undecided_since is not None and t_ns >= self._undecided_since + _LOGIN_HOLD_NS:
            self.sent.force()  # as the recorder does: what only a clock decides is masked, never shown
            self._tell_decided()
        timeout = self.context.hold_timeout_ns
        for _, _, held in [h for h in self._holds.values() if t_ns - h[2].since_ns >= timeout]:
            self._let_go(held, None, False, Cause(Source.TIMEOUT, text=f"{timeout / 1e9:g} s"), t_ns)
        for lane in self.lanes.values():
            lane.wake(t_ns)
        return self._done(t_ns)

    # -- control commands ------------------------------------------------------------------------

    def schedule(self, fault: Fault, t_ns: int) -> list[Command]:
        """A fault was added (or the connection opened): a reset or close after a time waits for its timer."""
        at = fault.timer_ns(self.opened_ns)
        conns = fault.spec.select.conns
        if at is not None and not (conns and self.conn not in conns) and not self.gone:
            self._timed.append((at, fault))
        return self._done(t_ns)

    def inject(self, direction: Direction, data: bytes, cause: Cause, t_ns: int) -> list[Command]:
        """Send ``data`` toward the receiver of ``direction`` after what is
        already decided.  ``Closing`` once a side is gone; ``Full`` when too
        much already waits in that direction, or its receiver was passed its FIN
        (nothing can be written after it)."""
        if self.closing or self.lanes[direction].eof_passed:
            raise Closing(f"connection {self.conn} is closing")
        self._inject(direction, data, cause, t_ns)
        self.lanes[direction].pump(t_ns)
        return self._done(t_ns)

    def release(self, held: Held, data: bytes | None, drop: bool, cause: Cause, t_ns: int) -> list[Command]:
        """Let a held frame go: as it is, as ``data``, or not at all (``drop``)."""
        if self.closing:
            raise Closing(f"connection {self.conn} is closing")
        self._let_go(held, data, drop, cause, t_ns)
        return self._done(t_ns)

    # -- state -----------------------------------------------------------------------------------

    def may_read(self, direction: Direction) -> bool:
        """Flow control: read the sender of ``direction`` only while its lane has room."""
        return self.lanes[direction].may_read()

    def deadline(self) -> int | None:
        times = [at for at, _ in self._timed]
        if self._undecided_since is not None:
            times.append(self._undecided_since + _LOGIN_HOLD_NS)
        timeout = self.context.hold_timeout_ns
        times += [held.since_ns + timeout for _, _, held in self._holds.values()]
        times += [t for lane in self.lanes.values() if (t := lane.deadline()) is not None]
        return min(times) if times and not self.gone else None

    # -- what the lanes ask (LaneOwner) -------------------------------------------------------------

    def idle(self) -> bool:
        return self.context.stages.idle

    def saw(self, direction: Direction, item: Item, t_ns: int) -> None:
        """Follow the handshake as the session model does (see ``session.py``)."""
        if direction is S2C and item.kind is ItemKind.HANDSHAKE:
            c2s = self.lanes[C2S]
            if item.raw == SENDCHKPASS:
                c2s.framer.expect_password()
            elif item.raw in VERDICTS:
                c2s.password_closed(t_ns)

    def decide(self, lane: Lane, item: Item, index: int, offset: int, t_ns: int) -> Frame:
        """A frame through the stages (a password through none); the lane tells
        its interventions, now if it is not delivered, else when it is."""
        direction = lane.direction
        context = self.context
        observation = item_alone(item, direction, index, context.checksum_rule)
        frame = Frame(self.conn, direction, item, observation, t_ns, self.opened_ns, index, offset,
                      self._secret(direction, item, offset), context.redact)
        if item.kind is not ItemKind.PASSWORD:
            context.stages.frame(frame)
        return frame

    def hold(self, lane: Lane, frame: Frame, out: Out, t_ns: int) -> Held:
        held = self.context.held.add(frame, t_ns)
        self._holds[held.id] = (lane, out, held)
        shown = held.shown
        self._tell(Intervention(self.conn, t_ns, frame.direction, Action.HOLD,
                                Cause(Source.INTERCEPT, text=frame.hold or ""), shown, shown, frame.kind.value,
                                f"held as #{held.id}", frame.index, held.id, frame.secret, frame.offset))
        return held

    def inject_from_stage(self, direction: Direction, data: bytes, cause: Cause, t_ns: int) -> None:
        self._inject(direction, data, cause, t_ns)

    def tell(self, event: Intervention) -> None:
        self._tell(event)

    def deliver(self, direction: Direction, data: bytes, t_ns: int, notes: list[tuple[int, Notes]],
                segments: Segments = ()) -> None:
        """Write ``data``; tell the interventions on the frames in it, with where
        each went, then the delivery.  What the server receives is masked by
        the recorder's rule over what the client *sent*: ``segments`` say which
        bytes of ``data`` are which of the client's (``passed``: all of it, as
        it came, from ``source``); bytes that are none of the client's (an
        injection, an edit) are not its password, unless they stand for a
        frame that may be one (``secret``).  A delivery waits to be told until
        the rule has decided its bytes."""
        base = self._delivered[direction]
        for at, group in notes:
            for note in group:
                self._tell(replace(note, delivered=base + at))
        if not data:
            return
        self._delivered[direction] = base + len(data)
        self._commands.append(Deliver(direction, data))
        if direction is S2C:
            self._tell(Delivered(self.conn, S2C, t_ns, data))
            return
        sent = self.sent
        if not self._undecided and sent.decided >= sent.received and sent.masked_end <= _first_source(segments):
            self._tell(Delivered(self.conn, C2S, t_ns, data))  # the usual case: decided, and past any password
            return
        self._undecided.append((segments, data, t_ns))
        self._tell_decided()
        if self._undecided and self._undecided_since is None:
            self._undecided_since = t_ns

    def end(self, how: Action, t_ns: int) -> None:
        """End the connection now (what is queued behind a frame's end never goes)."""
        self._commands.append(EndConnection(how))
        self.gone = True

    def pass_eof(self, direction: Direction) -> None:
        self._commands.append(PassEof(direction))

    def expired(self, direction: Direction, out: Out, t_ns: int) -> None:
        """A frame (or injection) due after its receiver was gone: never delivered, recorded as such."""
        held = out.held
        if held is not None:
            self._holds.pop(held.id, None)
            self.context.held.discard(held)
        for note in out.notes:
            self._tell(note)
        data = masked(out.data) if out.secret and self.context.redact else out.data
        self._tell(Intervention(self.conn, t_ns, direction, Action.EXPIRE, CLOSING, data, b"", out.kind,
                                "its receiver was gone before it was due: never delivered", out.index,
                                held.id if held is not None else 0, out.secret, out.offset))

    def slice_size(self, low: int, high: int) -> int:
        return self.context.rng.randint(low, high) if high > low else low

    # -- internals ----------------------------------------------------------------------------------

    def _secret(self, direction: Direction, item: Item, offset: int) -> bool:
        """A client frame that may be (part of) the password, by the recorder's
        rule over what the client sent: masked, or not yet decided."""
        return item.kind is ItemKind.PASSWORD or self.secret(direction, offset, len(item.raw))

    def secret(self, direction: Direction, offset: int, length: int) -> bool:
        """``length`` bytes the sender of ``direction`` sent from ``offset`` may be
        (part of) the password: masked by the rule, not yet decided, or from
        nowhere known (LaneOwner: bytes a lane passes on raw)."""
        if direction is S2C:
            return False
        sent = self.sent
        return offset < 0 or offset < sent.masked_end or offset + length > sent.decided

    def _inject(self, direction: Direction, data: bytes, cause: Cause, t_ns: int) -> None:
        try:
            self.lanes[direction].inject(data, t_ns, Intervention(self.conn, t_ns, direction, Action.INJECT, cause,
                                                                  b"", data))
        except Full as e:
            if cause.source is Source.INJECTION:
                raise
            self._tell(Intervention(self.conn, t_ns, direction, Action.DROP, cause, data, b"", "",
                                    f"injection refused: {e}"))

    def _let_go(self, held: Held, data: bytes | None, drop: bool, cause: Cause, t_ns: int) -> None:
        lane, out, _ = self._holds.pop(held.id)
        self.context.held.discard(held)
        before = out.data
        if drop:
            action, after = Action.DROP, b""
        elif data is not None and data != before:
            action, after = Action.EDIT, data
        else:
            action, after = Action.RELEASE, before
        shown = masked if held.hidden else bytes
        note = Intervention(self.conn, t_ns, held.direction, action, cause, shown(before), shown(after),
                            held.observation.item.kind.value, "", held.index, held.id, held.secret, held.offset)
        if drop:  # nothing of it is delivered: told now
            for earlier in out.notes:
                self._tell(earlier)
            self._tell(note)
            out.notes = ()
            lane.let_go(out, b"", (), t_ns)
        else:
            lane.let_go(out, after, (note,), t_ns)

    def _release_holds(self, t_ns: int, directions: tuple[Direction, ...]) -> None:
        """The connection is ending: held frames of ``directions`` (toward a
        side still there) go as they are, and the recording says so; the
        rest expire with their lane."""
        for lane, out, held in list(self._holds.values()):
            if lane.direction in directions:
                self._holds.pop(held.id)
                self.context.held.discard(held)
                shown = held.shown
                out.notes += (Intervention(self.conn, t_ns, held.direction, Action.RELEASE, CLOSING, shown, shown,
                                           held.observation.item.kind.value, "", held.index, held.id, held.secret,
                                           held.offset),)
                out.held = None

    def _timed_end(self, fault: Fault, t_ns: int) -> None:
        if self.gone or not fault.enabled or fault not in self.context.faults:
            return
        fault.hits += 1
        action = fault.action
        self._tell(Intervention(self.conn, t_ns, C2S, action, fault.cause,
                                detail=f"the proxy {action}s the connection"))
        if action is Action.CLOSE:  # a close on a timer delivers what waits first (held frames as they are)
            self._release_holds(t_ns, (C2S, S2C))
            for lane in self.lanes.values():
                lane.flush(t_ns)
        self.end(action, t_ns)

    def _tell(self, event: Data | Delivered | Intervention) -> None:
        self._commands.append(Tell(event))

    def _tell_decided(self) -> None:
        """Tell the deliveries to the server whose bytes the rule has decided,
        in order: the masked runs (but CR and LF) as secret, the rest not."""
        sent, undecided = self.sent, self._undecided
        while undecided and _decided(undecided[0][0], sent.decided):
            segments, data, t_ns = undecided.popleft()
            at = 0
            for start, stop in _masked_runs(segments, data, sent.masked_end):
                if start > at:
                    self._tell(Delivered(self.conn, C2S, t_ns, data[at:start]))
                self._tell(Delivered(self.conn, C2S, t_ns, data[start:stop], True))
                at = stop
            if at < len(data):
                self._tell(Delivered(self.conn, C2S, t_ns, data[at:]))
        if not undecided:
            self._undecided_since = None

    def _done(self, t_ns: int) -> list[Command]:
        """The commands so far, and a new wake-up time if it changed.  Both
        lanes are pumped first: a stage may have injected into the other one."""
        busy = False
        for lane in self.lanes.values():
            if lane.busy:
                lane.pump(t_ns)
                busy = True
        deadline = self.deadline() if busy or self._timed or self._holds or self._undecided or \
            self._wake is not None else None
        if deadline != self._wake:
            self._wake = deadline
            self._commands.append(WakeAt(deadline))
        commands, self._commands = self._commands, []
        return commands


def _first_source(segments: Segments) -> int:
    """Where the first of the client's bytes in a delivery began in its stream
    (a delivery of none of the client's bytes: as if past any password, unless secret)."""
    for _, _, source, secret in segments:
        if secret and source < 0:
            return -1
        if source >= 0:
            return source
    return 1 << 62


def _decided(segments: Segments, decided: int) -> bool:
    return all(source < 0 or source + length <= decided for _, length, source, _ in segments)


def _masked_runs(segments: Segments, data: bytes, masked_end: int) -> list[tuple[int, int]]:
    """The [start, stop) runs of ``data`` to mask, CR and LF left out: the
    client's bytes the rule masks, and all of a secret segment not the client's."""
    runs: list[tuple[int, int]] = []
    for at, length, source, secret in segments:
        if source >= 0:
            stop = at + max(0, min(length, masked_end - source))
        else:
            stop = at + length if secret else at
        runs += [m.span() for m in _MASKABLE.finditer(data, at, stop)]
    return runs
