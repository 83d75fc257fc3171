"""The running ``whiztap record``: proxy and writer process wired together.

Kept apart from the click command so tests can run a recorder in their own
event loop, and so the command module stays cheap to import.
"""

from __future__ import annotations

import asyncio
import sys
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.recording.notice import Notice
from whiztap.sniffer.record.consumers import Consumer, Consumers
from whiztap.sniffer.record.feed import WriterError, WriterProcess
from whiztap.sniffer.nettext import show_address
from whiztap.sniffer.record.metadata import base_metadata
from whiztap.sniffer.record.proxy import Connection, RecordingProxy
from whiztap.sniffer.record.summary import clock_text

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.control_endpoint import Endpoint
    from whiztap.sniffer.mitm.control_server import ControlServer
    from whiztap.sniffer.mitm.controller import Controller
    from whiztap.sniffer.record.mirror import Mirror
    from whiztap.sniffer.record.trigger import RingSettings


class StartError(WhiztapError):
    """The recording could not start (beyond the writer and the listening
    address, which raise their own); one line for the user."""


@dataclass(frozen=True)
class MiddleSettings:
    """The proxy as the man in the middle (docs/faults.md): faults (parsed
    SPECs), fault files, the control API's endpoint, scripts, the seed for
    chance and the hold timeout."""

    faults: tuple = ()
    fault_files: tuple[str, ...] = ()
    control: Endpoint | None = None  # a Unix socket or TCP (with its token), sniffer/mitm/control_endpoint.py
    scripts: tuple[str, ...] = ()
    seed: int | None = None
    hold_timeout: float = 60.0
    always: bool = False  # in the middle from the start with nothing configured (the TUI, the pytest fixture)

    @property
    def wanted(self) -> bool:
        return bool(self.always or self.faults or self.fault_files or self.control or self.scripts)


@dataclass(frozen=True)
class RecordSettings:
    listen: tuple[str, int]
    upstream: tuple[str, int]
    output: str
    split_size: int | None = None
    split_duration: float | None = None
    keep_secrets: bool = False
    checksum_rule: str = "dev-sum"
    quiet: bool = False
    analyze: bool = False
    connect_timeout: float = 5.0
    limits: Limits = Limits()
    # replace files at the recording's names (the command checked them at start,
    # and refuses unless --force); False: a name taken while recording stops it
    overwrite: bool = True
    when_behind: str = "pause"  # what happens to the connections that put the writer behind: "pause" or "gap"
    # (host, port): also serve the recording live to the Foxglove app (sniffer/record/live.py); port 0 picks one
    foxglove: tuple[str, int] | None = None
    middle: MiddleSettings = MiddleSettings()
    # the user's own metadata keys (--meta KEY=VALUE, already checked by user_metadata), for fleet reports
    meta: tuple[tuple[str, str], ...] = ()
    mirror: tuple[str, int] | None = None  # --mirror HOST:PORT: shadow traffic (sniffer/record/mirror.py)
    ring: RingSettings | None = None  # --ring: a window and an incident file per trigger (sniffer/record/ring.py)


class Recording:
    """A proxy recording into a writer process; ``start()``, then ``stop()``.

    ``echo`` receives each line meant for the user (connections, violations);
    ``stopped`` is set when the recording has to end on its own (write error).
    """

    def __init__(self, settings: RecordSettings, echo: Callable[[str], None] | None = None,
                 consumers: Iterable[Consumer] = (), warn: Callable[[str], None] | None = None) -> None:
        """``consumers`` receive every traffic event the file gets, from the
        first (the TUI's tap), each isolated: one that raises is reported once
        and cut off, and the recording goes on."""
        self.settings = settings
        self.echo = echo or (lambda line: None)
        self.warn = warn or (lambda text: print(text, file=sys.stderr, flush=True))
        self.controller: Controller | None = None
        self.control_url: str | None = None  # the control API's socket path, or http://HOST:PORT
        self.control_token: str | None = None  # the bearer token a TCP control API takes
        self._control: ControlServer | None = None
        self.consumers = Consumers(self._consumer_failed)
        self._extra = tuple(consumers)
        self.stopped = asyncio.Event()
        self.writer: WriterProcess | None = None
        self.proxy: RecordingProxy | None = None
        self.summary: dict | None = None
        self.mirror: Mirror | None = None  # with settings.mirror, once started

    @property
    def port(self) -> int:
        """The port clients connect to, once started (0 before)."""
        return self.proxy.port if self.proxy is not None else 0

    @property
    def error(self) -> str | None:
        return self.writer.error if self.writer is not None else None

    @property
    def control_text(self) -> str | None:
        """Where the control API is, as the start line and the TUI say it: its
        socket, or its URL and token, which 'whiztap ctl' takes as they are shown."""
        if self.control_url is None:
            return None
        return self.control_url if self.control_token is None else f"{self.control_url} token {self.control_token}"

    @property
    def foxglove_url(self) -> str | None:
        """Where the Foxglove app connects (``ws://HOST:PORT``, the bound port), with ``foxglove`` set."""
        return self.writer.ready.get("foxglove") if self.writer is not None else None

    async def start(self) -> None:
        """Bind, serve the control API (if asked), start the writer, accept.
        Raises WriterError, StartError (the control API), OSError (bind),
        FaultSpecError or ScriptError (a fault file or script that does not load)."""
        s = self.settings
        self.controller = self._controller()
        self.proxy = proxy = RecordingProxy(*s.listen, *s.upstream, self.consumers,
                                            connect_timeout=s.connect_timeout, on_opened=self._opened,
                                            on_closed=self._closed, controller=self.controller)
        await proxy.start(serving=False)
        try:
            await self._serve_control()  # before the writer: a taken port leaves no recording behind
        except StartError:
            await proxy.close()
            raise
        start_ns = proxy.clock()
        listen = proxy.listen_text
        middle = self.controller.metadata() if self.controller is not None else {}
        if s.mirror is not None:  # --mirror: the second server, among whiztap's keys
            middle = {**middle, "mirror": show_address(*s.mirror)}
        metadata = base_metadata("proxy", s.keep_secrets, s.checksum_rule, start_ns, listen=listen,
                                 upstream=proxy.upstream_text, split_size=s.split_size,
                                 split_duration=s.split_duration, user=dict(s.meta), **middle)
        config = {"path": s.output, "metadata": metadata, "keep_secrets": s.keep_secrets,
                  "checksum_rule": s.checksum_rule, "analyze": s.analyze, "start_ns": start_ns,
                  "limits": s.limits.as_dict(),
                  "split_size": s.split_size, "overwrite": s.overwrite,
                  "split_duration_ns": int(s.split_duration * 1e9) if s.split_duration else None,
                  "started": {"detail": f"proxy {listen} -> {proxy.upstream_text}"}, "foxglove": s.foxglove}
        if s.ring is not None:
            config["ring"] = s.ring.config()
        self.writer = writer = WriterProcess(config, s.when_behind)
        writer.on_hold = proxy.hold
        writer.on_violation = self._violation
        writer.on_error = lambda message: self.stopped.set()
        writer.on_warning = self.warn
        writer.on_file = lambda path: self.echo(f"finished {path}")
        if self.controller is not None:  # GET /state's verdict: the writer's, as analyze will judge the file
            self.controller.verdict = lambda: writer.verdict
            self.controller.log = lambda name, line, t_ns: writer.notice(Notice(t_ns, name, line))  # on /log
        if s.mirror is not None:
            self._start_mirror(config, writer)
        self.consumers.add(writer)
        for consumer in self._extra:
            self.consumers.add(consumer)
        try:
            await writer.start()
        except WriterError:
            await proxy.close()
            if self._control is not None:
                await self._control.stop()
            raise
        await proxy.serve()

    def _start_mirror(self, config: dict, writer: WriterProcess) -> None:
        """--mirror: the writer pairs (``config["mirror"]``), the proxy feeds the mirror."""
        from whiztap.sniffer.record.mirror import Mirror

        s, proxy = self.settings, self.proxy
        assert s.mirror is not None and proxy is not None  # asked, and started
        config["mirror"] = config["metadata"]["mirror"]
        self.mirror = Mirror(*s.mirror, s.connect_timeout, proxy.clock, writer, self.warn)
        writer.on_mirror = self.mirror.view.update

    async def stop(self, detail: str = "recording stopped") -> dict | None:
        """Close every connection, finish the file; the writer's summary."""
        if self._control is not None:
            await self._control.stop()
        proxy, writer = self.proxy, self.writer
        if proxy is None or writer is None:  # it never started: no file
            return None
        await proxy.close(detail)
        if self.mirror is not None:
            self.mirror.close()
        quiet = self.controller.end() if self.controller is not None else []  # faults that chose no frame: said
        self.summary = await writer.stop(proxy.clock(), detail)
        if self.summary is not None and self.mirror is not None:  # what the pairing found, in the end
            self.summary["mirror"] = self.mirror.view.final
        if self.summary is not None and quiet:
            self.summary["quiet_faults"] = [f"{fault.name} ({fault.spec.text})" for fault in quiet]
        return self.summary

    def _controller(self) -> Controller | None:
        """The control layer, when the proxy is to stand in the middle.
        Raises FaultSpecError (a fault file), StartError (a fault file's name
        that is taken or a number), ScriptError (a script that does not load)."""
        middle = self.settings.middle
        if not middle.wanted:
            return None
        from whiztap.sniffer.mitm.controller import ControlError, Controller, add_start_faults

        s = self.settings
        controller = Controller(seed=middle.seed, hold_timeout=middle.hold_timeout, checksum_rule=s.checksum_rule,
                                limits=s.limits, redact=not s.keep_secrets, report=self.warn)
        try:
            add_start_faults(controller, middle.fault_files, middle.faults)
        except ControlError as e:  # a name taken or a number, one fault too many
            raise StartError(str(e)) from None
        if middle.scripts:
            from whiztap.sniffer.mitm.scripts import load_script

            for path in middle.scripts:
                controller.add_script(load_script(path))
        return controller

    async def _serve_control(self) -> None:
        endpoint = self.settings.middle.control
        if endpoint is None or self.controller is None:
            return
        from whiztap.sniffer.mitm.control_endpoint import EndpointError
        from whiztap.sniffer.mitm.control_server import ControlServer

        self._control = control = ControlServer(self.controller, endpoint)
        try:
            await control.start()
        except EndpointError as e:
            raise StartError(f"cannot serve the control API: {e}") from None
        except OSError as e:
            raise StartError(f"cannot serve the control API on {endpoint}: {e.strerror or e}") from None
        self.control_url, self.control_token = control.url, control.token
        if not endpoint.loopback:
            self.warn(f"warning: the control API listens on {control.endpoint}, which other "
                      f"machines may reach: whoever has its token can drop, edit and inject the traffic")

    def _opened(self, conn: Connection) -> None:
        self.echo(f"#{conn.id} opened from {conn.client_addr}")
        if self.mirror is not None:
            conn.mirror = self.mirror.open(conn.id)

    def _closed(self, conn: Connection) -> None:
        if self.mirror is not None:
            self.mirror.client_closed(conn.id)
        seconds = (conn.proxy.clock() - conn.opened_ns) / 1e9
        if conn.upstream_failed:
            self.echo(f"#{conn.id} reset after {seconds:.2f} s: {conn.detail}; the client's connection was reset "
                      f"(c2s {conn.client.received} B, not forwarded)")
            return
        self.echo(f"#{conn.id} closed by {conn.closed_by} after {seconds:.2f} s ({conn.detail}): "
                  f"c2s {conn.client.received} B, s2c {conn.upstream.received} B")

    def _consumer_failed(self, consumer: Consumer, error: Exception) -> None:
        """A consumer raised: it gets no more events; the file and the traffic go on.
        The writer never raises (``WriterProcess.receive``); if it did, the
        recording could not go on, and stops with the reason."""
        writer = self.writer
        if writer is not None and consumer is writer:
            writer.fail(f"recording failed: {type(error).__name__}: {error}")
            return
        self.echo(f"{type(consumer).__name__} stopped receiving traffic: {type(error).__name__}: {error}")

    def _violation(self, v: dict) -> None:
        where = f" frame #{v['frame_index']} {v['frame_text']!r}" if "frame_index" in v else ""
        self.echo(f"! {v['rule_id']} ({v['severity']}) conn #{v['conn']} at {clock_text(v['t_ns'])}"
                  f"{where}: {v['detail']}")

