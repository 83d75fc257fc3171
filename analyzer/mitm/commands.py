"""What the middle's sans-IO core asks of the shell around it.

The core (``core.py``) takes events (bytes a side sent and when, a side's FIN
or its end, a timer, a control command) and answers each with a list of these
commands, carried out in order by whatever runs it: the proxy's asyncio shell
(``whiztap.sniffer.mitm.shell``), or a test on a fake clock.  The core never
touches a socket, a loop or a clock; these are all it can ask for.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.traffic import Action, Data, Delivered, Intervention


@dataclass(frozen=True, slots=True)
class Deliver:
    """Write ``data`` to the receiver of ``direction`` (the server for c2s)."""

    direction: Direction
    data: bytes


@dataclass(frozen=True, slots=True)
class PassEof:
    """The sender of ``direction`` sent its FIN and everything before it is
    delivered: shut down the receiver's writing half."""

    direction: Direction


@dataclass(frozen=True, slots=True)
class EndConnection:
    """End both sides now: ``Action.RESET`` (a TCP reset) or ``Action.CLOSE`` (a normal close)."""

    how: Action


@dataclass(frozen=True, slots=True)
class Tell:
    """Hand a traffic event to the proxy's consumers (the recorder, the TUI, Foxglove)."""

    event: Data | Delivered | Intervention


@dataclass(frozen=True, slots=True)
class WakeAt:
    """Call ``wake`` at ``t_ns`` (on the clock the core is given), or never (None)."""

    t_ns: int | None


Command = Deliver | PassEof | EndConnection | Tell | WakeAt


class MiddleRefused(WhiztapError):
    """A control command the core cannot carry out; one line saying why."""


class Closing(MiddleRefused):
    """The connection is ending: nothing more can be sent on it (HTTP 409)."""


class Full(MiddleRefused):
    """Too much already waits to be delivered in that direction (HTTP 429)."""
