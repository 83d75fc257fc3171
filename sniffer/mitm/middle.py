"""One proxied connection with the proxy in the middle: its two lanes and its end.

The proxy's ``Connection`` gets a ``Middle`` when the proxy runs with a
``Controller`` (any of --fault, --faults, --control, --script): its reads then
go through the lanes instead of straight to the other side.  The Middle
follows the handshake (a password is framed only once the server asks for it
and ends when the server judges it, as in the session model), carries out the
connection's end when a fault asks for it, and keeps the proxy's flow control
told of what its lanes hold.
"""

from __future__ import annotations

import asyncio
import socket
import struct
from typing import Any

from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.redaction import HOLD_LIMIT_S, LoginMask
from whiztap.analyzer.traffic import Delivered, Intervention
from whiztap.sniffer.mitm.faults import Fault
from whiztap.sniffer.mitm.frame import Frame
from whiztap.sniffer.mitm.lane import HIGH_WATER, Lane, _Out

C2S, S2C = Direction.C2S, Direction.S2C
_ASKS = b"sendchkpass"
_VERDICTS = (b"readytogo", b"Failed Validation")
_LINGER_NOW = struct.pack("ii", 1, 0)  # SO_LINGER on, 0 s: close() sends a TCP reset


class Middle:
    def __init__(self, controller: Any, connection: Any) -> None:
        """``controller``: the Controller (controller.py); ``connection``: the
        proxy's Connection (sniffer/record/proxy.py), which this package does
        not import: the proxy builds on it, not the other way round."""
        self.controller = controller
        self.connection = connection
        self.conn_id = connection.id
        self.clock = controller.clock
        self.rng = controller.rng
        self.stages = controller.stages
        self.opened_ns = controller.clock()
        limits = controller.limits
        self.lanes = {d: Lane(self, d, Framer(limits.max_frame, limits.max_image)) for d in (C2S, S2C)}
        self.gone = False
        self.login = LoginMask()  # the recorder's rule for passwords, over what the server received
        self._undecided: list[tuple[int, bytes, int]] = []  # (offset, bytes, time) delivered to the server, not yet told
        self._login_timer: asyncio.TimerHandle | None = None
        self._timers: list[asyncio.TimerHandle] = []

    def emit(self, event: object) -> None:
        self.controller.emit(event)

    def may_read(self, direction: Direction) -> bool:
        return self.lanes[direction].queued <= HIGH_WATER

    # -- what lanes and stages ask ------------------------------------------------------------

    def saw(self, lane: Lane, item: Item) -> None:
        """Follow the handshake as the session model does (see ``session.py``)."""
        if lane.direction is S2C and item.kind is ItemKind.HANDSHAKE:
            c2s = self.lanes[C2S]
            if item.raw == _ASKS:
                c2s.framer.expect_password()
            elif item.raw in _VERDICTS:
                c2s.password_closed(item.t_end_ns)

    # -- what each side received: Delivered events, a password kept secret ---------------------

    def delivered(self, direction: Direction, data: bytes, t_ns: int) -> None:
        """The proxy wrote ``data`` toward the receiver of ``direction``.  What
        the server receives is judged by the recorder's own rule for passwords
        (``LoginMask``, the rule /tcp/reads is masked by), over the bytes the
        server received and sent; the event waits until the rule has decided,
        so the recording and the TUI mask exactly the bytes they mask in what
        the client sent."""
        if direction is S2C:
            self.emit(Delivered(self.conn_id, S2C, t_ns, data))
            return
        login = self.login
        self._undecided.append((login.received, data, t_ns))
        login.client(data)
        self._tell_decided()
        if self._undecided and self._login_timer is None:
            self._login_timer = asyncio.get_running_loop().call_later(HOLD_LIMIT_S, self._undecided_too_long)

    def server_bytes(self, data: bytes) -> None:
        self.login.server(data)
        self._tell_decided()

    def server_ended(self) -> None:
        """The server sent its FIN: it will say nothing more about a login."""
        self.login.server_ended()
        self._tell_decided()

    def _undecided_too_long(self) -> None:
        """As the recorder does: what only a clock decides is masked, never shown."""
        self._login_timer = None
        self.login.force()
        self._tell_decided()

    def _tell_decided(self) -> None:
        login, undecided = self.login, self._undecided
        while undecided and login.decided >= undecided[0][0] + len(undecided[0][1]):
            offset, data, t_ns = undecided.pop(0)
            _, spans = login.apply(offset, data)
            at = 0
            for start, length in spans:  # the masked runs are secret, the rest (line breaks, after) is not
                if start > at:
                    self.emit(Delivered(self.conn_id, C2S, t_ns, data[at:start]))
                self.emit(Delivered(self.conn_id, C2S, t_ns, data[start:start + length], True))
                at = start + length
            if at < len(data):
                self.emit(Delivered(self.conn_id, C2S, t_ns, data[at:]))
        if not undecided and self._login_timer is not None:
            self._login_timer.cancel()
            self._login_timer = None

    def new_frame(self, lane: Lane, item: Item, observation: object, t_ns: int) -> Frame:
        return Frame(self.conn_id, lane.direction, item, observation, t_ns, self.opened_ns)  # type: ignore[arg-type]

    def hold(self, lane: Lane, out: _Out, frame: Frame) -> None:
        if frame.hold is not None:
            out.held = self.controller.held.hold(lane, out, frame)

    def end(self, how: str) -> None:
        if how == "reset":
            self.reset()
        else:
            self.connection.close_both("proxy", "closed by a fault")

    def reset(self) -> None:
        """Both sides get a TCP reset now."""
        for leg in (self.connection.client, self.connection.upstream):
            transport = leg.transport
            if transport is None or leg.lost:
                continue
            sock = transport.get_extra_info("socket")
            if sock is not None:
                try:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_NOW)
                except OSError:
                    pass
        connection = self.connection
        if connection.closed_by is None:
            connection.closed_by, connection.detail = "proxy", "reset by a fault"
        self.gone = True
        connection.abort()

    def pass_eof(self, lane: Lane) -> None:
        """A lane delivered everything before its sender's FIN: pass the FIN on."""
        self.connection.pass_eof(self.connection.client if lane.direction is C2S else self.connection.upstream)

    def sync(self) -> None:
        self.connection.client.sync()
        self.connection.upstream.sync()

    # -- timers, injection, the end --------------------------------------------------------------

    def schedule(self, fault: Fault) -> None:
        """A reset or close after a time (``Fault.timer_ns``) acts on a timer."""
        at = fault.timer_ns(self.opened_ns)
        spec = fault.spec
        if at is None or (spec.select.conns and self.conn_id not in spec.select.conns):
            return
        delay = max(0.0, (at - self.clock()) / 1e9)
        self._timers.append(asyncio.get_running_loop().call_later(delay, self._timed_end, fault))

    def _timed_end(self, fault: Fault) -> None:
        if self.gone or not fault.enabled or fault not in self.controller.faults:
            return
        fault.hits += 1
        action = fault.spec.action
        self.emit(Intervention(self.conn_id, self.clock(), C2S, action, fault.cause, b"", b"", "",
                               f"the proxy {action}s the connection"))
        if action == "close":
            for lane in self.lanes.values():
                lane.flush()
        self.end(action)

    def inject(self, direction: Direction, data: bytes, cause: str) -> None:
        self.lanes[direction].inject(data, cause, self.clock())

    def closing(self) -> None:
        """One side is gone: deliver what waits (held frames as they are), then stop."""
        for lane in self.lanes.values():
            if lane.target is not None and not lane.target.is_closing():
                lane.flush()
        self.login.end()  # undecided client bytes are masked
        self._tell_decided()

    def close(self) -> None:
        self.gone = True
        self.login.end()
        self._tell_decided()
        for timer in self._timers:
            timer.cancel()
        for lane in self.lanes.values():
            lane.stop_timers()
