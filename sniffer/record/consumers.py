"""The proxy's traffic events, handed to each of its consumers, each isolated.

The proxy says what it forwards as the typed events of
``whiztap.analyzer.traffic`` and hands each to every consumer (the writer
process, the TUI's tap), as mitmproxy's addon manager hands its events to
addons.  A consumer that raises is cut off: it is reported once (``on_failure``)
and gets nothing more, while the proxy forwards on and the other consumers keep
receiving.  A broken view or a bug in one consumer must never stop traffic or
another consumer's recording.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Protocol

from whiztap.analyzer.traffic import TrafficEvent


class Consumer(Protocol):
    """Something that takes traffic events, one at a time, in the order they happened."""

    def receive(self, event: TrafficEvent) -> None: ...


Failure = Callable[[Consumer, Exception], None]


class Consumers:
    """A fan-out of traffic events: ``receive(event)`` gives it to every
    consumer, in the order they were added; one that raises is dropped and
    ``on_failure(consumer, error)`` is told, once."""

    def __init__(self, on_failure: Failure) -> None:
        self.on_failure = on_failure
        self._receivers: tuple[tuple[Consumer, Callable[[TrafficEvent], None]], ...] = ()

    def add(self, consumer: Consumer) -> None:
        """From the next event on, ``consumer`` receives them too."""
        self._receivers += ((consumer, consumer.receive),)

    def receive(self, event: TrafficEvent) -> None:
        """Hot loop (once per TCP read the proxy forwards): the receivers are
        kept as bound methods in a tuple, and a ``try`` costs nothing until
        something raises."""
        for consumer, receive in self._receivers:
            try:
                receive(event)
            except Exception as error:  # whatever a consumer does wrong, traffic goes on
                self._drop(consumer, error)

    def _drop(self, consumer: Consumer, error: Exception) -> None:
        self._receivers = tuple(r for r in self._receivers if r[0] is not consumer)
        self.on_failure(consumer, error)
