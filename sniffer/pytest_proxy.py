"""The object behind the pytest plugin's ``whiztap_proxy`` fixture: the recording
proxy in the middle between the client under test and the target, driven from
a test (docs/pytest-plugin.md, docs/faults.md).

A module of its own, loaded only when a test asks for the fixture: the plugin
itself imports nothing but pytest and the standard library, and this needs the
proxy, the controller and the writer.

The proxy and its ``Controller`` run on the plugin's background event loop,
and the controller is not thread-safe, so every method here runs its work on
that loop and waits for the answer: a synchronous test and an asyncio test (on
a loop of its own) call them alike.
"""

from __future__ import annotations

import shutil
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest

from whiztap.analyzer.traffic import Intervention, TrafficEvent
from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.mitm.controller import ControlError, Controller
from whiztap.analyzer.mitm.faults import Fault
from whiztap.sniffer.record.record_run import MiddleSettings, Recording, RecordSettings

SEED = 0  # prob:, jitter: and slice ranges choose alike on every run
CONNECTION_WAIT_S = 2.0  # how long inject() waits for the client's connection to reach the proxy
CALL_TIMEOUT_S = 10.0

Run = Callable[..., Any]  # BackgroundLoop.run: a coroutine run on the proxy's loop, its result


class FaultHandle:
    """A fault a test added with ``WhiztapProxy.fault``: in force until
    ``remove()``, or until the ``with`` block it opens ends."""

    def __init__(self, proxy: WhiztapProxy, fault: Fault) -> None:
        self._proxy = proxy
        self._fault = fault  # the proxy's loop owns it; reading a field from here is safe
        self.id, self.name, self.spec = fault.id, fault.name, fault.spec.text
        self.removed = False

    @property
    def hits(self) -> int:
        """How many times it acted so far."""
        return self._fault.hits

    def remove(self) -> None:
        """Take the fault out (once; again is a no-op)."""
        if not self.removed:
            self.removed = True
            self._proxy.call(self._proxy.controller.remove_fault, self.id)

    def __enter__(self) -> FaultHandle:
        return self

    def __exit__(self, *exc: object) -> None:
        self.remove()


class _Interventions:
    """A consumer of the proxy's traffic events that keeps the interventions.
    In memory, as they happen: the recording's /interventions is only readable
    once the file is finished."""

    def __init__(self) -> None:
        self.events: list[Intervention] = []

    def receive(self, event: TrafficEvent) -> None:
        if type(event) is Intervention:
            self.events.append(event)


class WhiztapProxy:
    """The recording proxy in the middle; ``start`` it on the background loop."""

    def __init__(self, run: Run, path: Path, target: tuple[str, int]) -> None:
        self._run = run
        self._kept = _Interventions()
        # the control API on a socket in a folder of its own: it always can be
        # made (a runtime folder may not), and a test's is no user's default
        self._folder = Path(tempfile.mkdtemp(prefix="whiztap-"))
        middle = MiddleSettings(seed=SEED, always=True, control=Endpoint(path=str(self._folder / "control.sock")))
        settings = RecordSettings(("127.0.0.1", 0), target, str(path), quiet=True, middle=middle)
        self._recording = Recording(settings, consumers=[self._kept])
        self.recording = path
        self.host, self.port = "127.0.0.1", 0
        self.stopped = False
        self.connection_wait = CONNECTION_WAIT_S  # seconds inject() waits for the only connection

    def start(self) -> WhiztapProxy:
        try:
            self._run(self._recording.start())
        except BaseException:
            shutil.rmtree(self._folder, ignore_errors=True)
            raise
        self.port = self._recording.port
        return self

    @property
    def controller(self) -> Controller:
        controller = self._recording.controller
        assert controller is not None  # this proxy always stands in the middle
        return controller

    @property
    def address(self) -> str:
        """Where the client under test connects: "127.0.0.1:PORT"."""
        return f"{self.host}:{self.port}"

    @property
    def control(self) -> str:
        """The control API's Unix socket, for ``whiztap ctl --control PATH``
        or a tool under test that drives the proxy over HTTP."""
        url = self._recording.control_url
        assert url is not None  # this proxy always serves its control API
        return url

    def call(self, function: Callable[..., Any], *args: Any) -> Any:
        """``function(*args)`` on the proxy's loop, and its result (or its exception)."""
        async def on_the_loop() -> Any:
            return function(*args)

        return self._run(on_the_loop(), timeout=CALL_TIMEOUT_S)

    def fault(self, spec: str, name: str = "") -> FaultHandle:
        """Add a fault (a SPEC, docs/faults.md) now; FaultSpecError (a
        ValueError naming the word) if it does not parse."""
        return FaultHandle(self, self.call(self.controller.add_fault, spec, name))

    def inject(self, *args: Any, force: bool = False) -> bytes:
        """``inject([conn,] "c2s"|"s2c", frame)``: send a typed frame (escaped
        text or console words) toward the server or the client, after what is
        queued; conn defaults to the only open connection.  ControlError (a
        ValueError) when the frame breaks a rule and not ``force``, or when no
        or several connections are open.  The bytes sent."""
        if len(args) not in (2, 3):
            raise TypeError("inject takes (direction, frame) or (conn, direction, frame)")
        conn, direction, frame = args if len(args) == 3 else (None, *args)
        if conn is None:
            conn = self._only_connection()
        return self.call(self.controller.inject, conn, direction, frame, force)

    def _only_connection(self) -> int:
        """The one open connection, waiting a little for it: a client that does
        no handshake may be connected before the proxy has accepted it."""
        deadline = time.monotonic() + self.connection_wait
        while True:
            conns = self.call(lambda: sorted(self.controller.cores))
            if len(conns) > 1:
                named = ", ".join(f"#{c}" for c in conns)
                raise ControlError(f"{len(conns)} connections are open through the proxy ({named}): "
                                   f"name one, as in inject({conns[-1]}, \"s2c\", ...)")
            if conns:
                return conns[0]
            if time.monotonic() >= deadline:
                raise ControlError("no connection is open through the proxy: connect the client to "
                                   "proxy.address first")
            time.sleep(0.01)

    def interventions(self, action: str | None = None) -> list[Intervention]:
        """Every change the proxy made so far, oldest first; only those of
        ``action`` ("drop", "inject", ...) if given."""
        return self.call(lambda: [e for e in self._kept.events if action is None or e.action == action])

    def state(self) -> dict:
        """The controller's state: faults (with their hits), connections, held frames."""
        return self.call(self.controller.state)

    def stop(self) -> Path:
        """Close the connections and finish the recording now (the fixture does
        it after the test otherwise); the recording's path."""
        if not self.stopped:
            self.stopped = True
            self._run(self._recording.stop())
            shutil.rmtree(self._folder, ignore_errors=True)
            if self._recording.error:
                pytest.fail(f"whiztap: recording {self.recording} failed: {self._recording.error}", pytrace=False)
        return self.recording
