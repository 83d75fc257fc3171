"""How a sniffer command runs its coroutine, and how it is told to stop.

One runner (uvloop: an asyncio.Protocol proxy forwards about twice as fast on
it, and its cheaper timers keep a replayed schedule tighter) and one set of
stop signals: Ctrl-C, SIGTERM, and SIGHUP from a closed terminal or ssh
session.  Imports stay inside the functions: 'whiztap --help' loads this module.
"""

from __future__ import annotations

import contextlib
import signal
from collections.abc import Callable, Coroutine, Iterator
from typing import Any, TypeVar

from whiztap.analyzer.cli.errors import fail

T = TypeVar("T")


def run(main: Coroutine[Any, Any, T]) -> T:
    """Run a command's coroutine on uvloop.  A Ctrl-C that comes before the
    coroutine listens for it (``stop_signals``) ends the command as
    'interrupted', one line and exit status 2 (click would add a blank line)."""
    import asyncio

    import uvloop

    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # started in the background by a script, the process inherits an ignored
        # SIGINT; restore it so that `kill -INT` stops the command as Ctrl-C does
        signal.signal(signal.SIGINT, signal.default_int_handler)
    try:
        with asyncio.Runner(loop_factory=uvloop.new_event_loop) as runner:
            return runner.run(main)
    except KeyboardInterrupt:
        fail("interrupted")


@contextlib.contextmanager
def stop_signals(stop: Callable[[], object]) -> Iterator[None]:
    """While the block runs (in the running loop), the stop signals call
    ``stop`` instead of killing the process, so that connections are closed and
    files finished; the usual handling is back afterwards."""
    import asyncio

    from whiztap.sniffer.record.writer import STOP_SIGNALS

    loop = asyncio.get_running_loop()
    for sig in STOP_SIGNALS:
        loop.add_signal_handler(sig, stop)
    try:
        yield
    finally:
        for sig in STOP_SIGNALS:
            loop.remove_signal_handler(sig)
