"""Faults in a replay: which ones a recording was made under, and the proxy
in the middle that applies them between the replay and its target.

A recording made with the proxy in the middle names its faults in two
places: the metadata (``faults``, the ones given at the start, and ``seed``)
and the ``cause`` of each /interventions message ("fault NAME: SPEC"), the
only trace of a fault added at run time through the control API.
``recorded_faults`` takes both, each fault once.  Holds, hand edits,
injections and scripts are not faults and are not re-applied: they were a
person's or a script's doing at one moment, not a rule a proxy can follow.

``FaultProxy`` is a ``RecordingProxy`` with a ``Controller`` on a free
loopback port: the replay connects to it instead of the target, so the
target sees what the recorded client's server saw, and the replay what the
recorded client saw.  It is the proxy ``whiztap record --fault`` runs, so a
fault does in a replay exactly what it did while recording.  Its traffic
events say when each connection reached the target, and, with ``--output``,
they are what the replay records (the server's reads, what each side was
delivered, and each intervention), as ``whiztap record`` would have.
"""

from __future__ import annotations

import asyncio
import json
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path

from whiztap.analyzer.mitm.spec import FaultSpec, FaultSpecError, parse_fault
from whiztap.analyzer.recording.format import TOPIC_INTERVENTIONS
from whiztap.analyzer.recording.scan import RecordingError, RecordingScan
from whiztap.analyzer.traffic import Closed, Opened, TrafficEvent, UpstreamConnected, UpstreamFailed
from whiztap.sniffer.mitm.controller import ControlError, Controller
from whiztap.sniffer.mitm.controller import middle_metadata as controller_metadata  # replay's own takes options
from whiztap.sniffer.nettext import reason, show_address
from whiztap.sniffer.record.proxy import RecordingProxy
from whiztap.sniffer.replay.options import ReplayError, ReplayOptions

LOOPBACK = "127.0.0.1"
_CAUSE = "fault "  # an intervention's cause when a fault did it: "fault NAME: SPEC"
_SETTLE_S = 1.0  # beyond --connect-timeout, for the proxy to say how its own connect went


@dataclass(frozen=True)
class RecordedFaults:
    """The faults a recording was made under, in the order they came into force, and its seed."""

    faults: tuple[FaultSpec, ...]
    seed: int | None


def fault_text(spec: FaultSpec) -> str:
    """A fault as the replay names it to people: ``fault NAME: SPEC``, or ``fault: SPEC``."""
    return f"fault {spec.name}: {spec.text}" if spec.name else f"fault: {spec.text}"


def middle_metadata(options: ReplayOptions) -> dict[str, str]:
    """The metadata of a recording made through the faults, as ``whiztap record``
    writes it, so that a replay's output can be replayed under them in turn."""
    return controller_metadata(options.faults, options.fault_seed)


# -- what a recording was made under ----------------------------------------------------------------


def recorded_faults(parts: Iterable[str | Path], metadata: dict[str, str]) -> RecordedFaults:
    """The faults of the recording in ``parts`` (a split one's files, in order)
    whose metadata is ``metadata``: those it started with, then those its
    interventions name that it did not; ReplayError (one line) for a fault or a
    seed that does not read."""
    paths = [Path(p) for p in parts]
    where = str(paths[0]) if paths else "the recording"
    if metadata.get("middle") != "yes":
        return RecordedFaults((), None)  # no proxy in the middle: no fault, and no /interventions
    faults = _started(where, metadata.get("faults", "[]"))
    names = {f.name for f in faults if f.name}
    unnamed = [f.text for f in faults if not f.name]  # at run time these were named fault-N
    for name, text in _caused(paths):
        if name in names:
            continue
        names.add(name)
        if text in unnamed:
            unnamed.remove(text)
            continue
        faults.append(_parse(where, text, name))
    return RecordedFaults(tuple(faults), _seed(where, metadata.get("seed", "")))


def _started(where: str, text: str) -> list[FaultSpec]:
    """The faults the metadata names (a JSON list of {"name", "spec"})."""
    try:
        listed = json.loads(text)
        if not isinstance(listed, list):
            raise TypeError("not a list")
        pairs = [(str(f.get("name") or ""), f["spec"]) for f in listed]
        if not all(isinstance(spec, str) for _, spec in pairs):
            raise ValueError("a spec that is not text")
    except (ValueError, TypeError, KeyError, AttributeError) as e:
        raise ReplayError(f"{where}: its metadata 'faults' is not a list of faults ({e})") from None
    return [_parse(where, spec, name) for name, spec in pairs]


def _parse(where: str, text: str, name: str) -> FaultSpec:
    try:
        return parse_fault(text, name)
    except FaultSpecError as e:
        raise ReplayError(f"{where}: a fault the recording was made under does not read here: {e}") from None


def _seed(where: str, text: str) -> int | None:
    try:
        return int(text) if text else None
    except ValueError:
        raise ReplayError(f"{where}: its metadata 'seed' is not a number: {text!r}") from None


def _caused(parts: list[Path]) -> Iterator[tuple[str, str]]:
    """(name, SPEC) of each fault the recording's /interventions name, once
    each, in the order they first acted."""
    seen: set[str] = set()
    for path in parts:
        try:
            with path.open("rb") as f:
                for _topic, _t, message in RecordingScan(f, (TOPIC_INTERVENTIONS,)).messages():
                    cause = message["cause"]
                    if cause in seen or not cause.startswith(_CAUSE):
                        continue
                    seen.add(cause)
                    name, colon, text = cause[len(_CAUSE):].partition(": ")
                    if colon and name and text:
                        yield name, text
        except OSError as e:
            raise ReplayError(f"{path}: cannot read ({e.strerror or e})") from None
        except RecordingError as e:
            raise ReplayError(f"{path}: {e}") from None


# -- the proxy in the middle --------------------------------------------------------------------------


def _report(line: str) -> None:
    """A fault that failed on a frame (the frame passed untouched): said on
    stderr, as ``whiztap record`` says it, never among the replay's results."""
    print(f"whiztap: {line}", file=sys.stderr, flush=True)


class FaultProxy:
    """The proxy in the middle of one replay (``start()``, ``reached()`` for each
    connection, ``close()``); ``record``, if given, gets every traffic event,
    and so does ``watch`` (the judge of the target's own side, ``server_side.py``)."""

    def __init__(self, options: ReplayOptions, record: Callable[[TrafficEvent], None] | None = None,
                 watch: Callable[[TrafficEvent], None] | None = None) -> None:
        self.controller = Controller(seed=options.fault_seed, checksum_rule=options.checksum_rule, report=_report)
        try:
            for spec in options.faults:
                self.controller.add_fault(spec)
        except ControlError as e:
            raise ReplayError(str(e)) from None
        host, port = options.address
        self.target = show_address(host, port)
        self.timeout = options.connect_timeout
        self.proxy = RecordingProxy(LOOPBACK, 0, host, port, self, connect_timeout=options.connect_timeout,
                                    controller=self.controller)
        self._record = record
        self._watch = watch
        self._clients: dict[int, str] = {}  # the proxy's connection -> the replay's local address
        self._upstream: dict[str, asyncio.Future[str | None]] = {}  # by that address: the failure, or None

    @property
    def clock(self) -> Callable[[], int]:
        """The time of the proxy's traffic events (an output recording must keep it too)."""
        return self.proxy.clock

    async def start(self) -> tuple[str, int]:
        """Listen; where the replay connects to instead of the target."""
        try:
            await self.proxy.start()
        except OSError as e:
            raise ReplayError(f"cannot listen on {LOOPBACK} for the faults' proxy: {reason(e)}") from None
        return LOOPBACK, self.proxy.port

    def receive(self, event: TrafficEvent) -> None:
        """The proxy's traffic events: whether each connection reached the
        target, and, with an output recording, everything, to it."""
        if isinstance(event, Opened):
            self._clients[event.conn] = event.client
        elif isinstance(event, (UpstreamConnected, UpstreamFailed)):
            client = self._clients.get(event.conn)
            if client is not None:
                outcome = self._outcome(client)
                if not outcome.done():
                    outcome.set_result(event.detail if isinstance(event, UpstreamFailed) else None)
        elif isinstance(event, Closed):
            self._clients.pop(event.conn, None)
        if self._watch is not None:
            self._watch(event)
        if self._record is not None:
            self._record(event)

    def _outcome(self, client: str) -> asyncio.Future[str | None]:
        future = self._upstream.get(client)
        if future is None:
            future = self._upstream[client] = asyncio.get_running_loop().create_future()
        return future

    async def reached(self, local: str) -> None:
        """Wait until the proxy has connected the replay's connection from
        ``local`` to the target: a target it cannot reach is a ReplayError,
        worded as when the replay connects to it itself."""
        try:
            failed = await asyncio.wait_for(asyncio.shield(self._outcome(local)), self.timeout + _SETTLE_S)
        except TimeoutError:
            failed = f"cannot connect to {self.target}: timed out"
        finally:
            self._upstream.pop(local, None)
        if failed:
            raise ReplayError(failed)

    async def close(self) -> None:
        """Close what is still open (the replay has judged it all by now)."""
        await self.proxy.close("replay finished")
