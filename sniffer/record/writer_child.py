"""The writer process's side of the recording pipe (``feed.py`` is the proxy's).

Run as ``python -m whiztap.sniffer.record.writer_child CONFIG``: one thread
reads the pipe, decodes the records (layout in ``feed.py``) back into traffic
events for a ``Recorder`` and reports on its stdout as JSON lines (ready,
violations for ``--analyze``, finished files, errors, the summary).  With
``--foxglove`` it also serves every message live (``live.py``; "ready" says
where).  It ignores SIGINT (Ctrl-C reaches the whole process group; the parent
decides when to stop) and finishes the file when the pipe closes, so even a
parent killed with SIGKILL leaves a finished recording.
"""

from __future__ import annotations

import json
import os
import select
import signal
import sys
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.recording.notice import Notice
from whiztap.analyzer.recording.stdout import drop_stdout
from whiztap.analyzer.traffic import (
    Data,
    Delivered,
    RecordingStopped,
    from_json,
    intervention_from_json,
)
from whiztap.sniffer.record.feed import (
    _DIRS,
    _HEAD,
    EXIT_WRITE_ERROR,
    REC_DATA,
    REC_DELIVERED,
    REC_INTERVENTION,
    REC_MIRROR,
    REC_NOTICE,
    SECRET,
    TICK_S,
    WRITER_NICE,
    WriterError,
)

if TYPE_CHECKING:
    from whiztap.analyzer.protocol.observations import Observation
    from whiztap.analyzer.protocol.rules import Violation
    from whiztap.sniffer.record.recorder import Recorder
    from whiztap.sniffer.record.mirror_record import MirrorRecorder
    from whiztap.sniffer.record.writer import RecordingFile

VERDICT_S = 0.25  # the verdict is reported at most this often
_SAYING = threading.Lock()  # the live server's threads (its gate, the SDK's log) say things too


def _say(message: dict) -> None:
    """One status line to the proxy, whole, whichever thread says it.  A proxy
    that is gone (killed on its own) hears nothing more, but the recording must
    still be finished: the first failed write points stdout at /dev/null and
    later ones go nowhere."""
    line = json.dumps(message).encode() + b"\n"
    with _SAYING:
        try:
            os.write(1, line)
        except OSError:  # EPIPE: nobody reads the other end any more
            drop_stdout()


def _warning(text: str) -> None:
    """Something the writer worked around (a part name taken, the live
    server's trouble): the proxy says it where its user sees warnings (stderr,
    or the TUI's notices), never this process's own stderr."""
    _say({"type": "warning", "message": text})


def _violation_report(conn: int, t_ns: int, violation: Violation, about: Observation | None, late: bool) -> None:
    from whiztap.analyzer.recording.encode import violation_message

    message = violation_message(conn, violation, about, t_ns, late=late, redact=True)
    _say({"type": "violation", **message})


def _apply(recorder: Recorder, buf: bytearray, mirror: MirrorRecorder | None = None) -> RecordingStopped | None:
    """Hot loop (once per read recorded): turn each whole record at the start of
    ``buf`` back into its traffic event for the recorder, and remove it; the
    stop event, if one came (nothing after it is read)."""
    head = _HEAD.size
    pos = 0
    n = len(buf)
    receive = recorder.receive
    try:
        while n - pos >= head:
            kind, conn, direction, t, length = _HEAD.unpack_from(buf, pos)
            end = pos + head + length
            if end > n:
                break
            payload = bytes(buf[pos + head:end])
            pos = end
            if kind == REC_DATA:
                receive(Data(conn, _DIRS[direction], t, payload))
                continue
            if kind == REC_DELIVERED:
                receive(Delivered(conn, _DIRS[direction & 1], t, payload, bool(direction & SECRET)))
                continue
            if kind == REC_INTERVENTION:
                receive(intervention_from_json(conn, _DIRS[direction], t, json.loads(payload)))
                continue
            if kind == REC_NOTICE:
                receive(Notice(**json.loads(payload)))
                continue
            if kind == REC_MIRROR:  # record --mirror (mirror_record.py)
                if mirror is not None:
                    mirror.receive(conn, bool(direction), t, payload)
                continue
            event = from_json(json.loads(payload))
            if type(event) is RecordingStopped:
                return event
            receive(event)
        return None
    finally:
        del buf[:pos]


class _VerdictReports:
    """In the middle, the verdict so far (``Recorder.verdict``) goes to the
    proxy when it changes, at most every ``VERDICT_S``: what ``GET /state`` serves."""

    def __init__(self, recorder: Recorder) -> None:
        self.recorder = recorder
        self.last: dict | None = None
        self.at = 0.0

    def report(self, now: float) -> None:
        if self.recorder.judge is None or now - self.at < VERDICT_S:
            return
        self.at = now
        current = self.recorder.verdict()
        if current is not None and current != self.last:
            self.last = current
            _say({"type": "verdict", **current})


def _ignore_signals(on_term: Callable[[int, object], None]) -> None:
    """Ctrl-C and a closed terminal reach the whole process group: the proxy
    decides when to stop and says so with a stop record (or dies, and the pipe
    closes).  A broken status pipe is an error to survive, not a death, and a
    file size limit an error to report."""
    for ignored in (signal.SIGINT, signal.SIGHUP, signal.SIGPIPE, signal.SIGXFSZ):
        signal.signal(ignored, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, on_term)


def _recording_file(config: dict[str, Any]) -> tuple[RecordingFile, dict[str, str]]:
    """The file, and with ``foxglove`` (host, port) one that also serves every
    message live (``live.py``; imported only then, so recording without it
    pays nothing); the server starts before the file is made, so a port in
    use leaves no file behind (raises WriterError)."""
    from whiztap.sniffer.record.writer import RecordingFile

    args = (config["path"], config["metadata"])
    if config.get("ring"):  # --ring: a window, and an incident file per trigger (ring.py)
        from whiztap.sniffer.record.ring import RingFile
        from whiztap.sniffer.record.trigger import Ring

        ring = config["ring"]
        return RingFile(*args, Ring(ring["duration_ns"], ring["max_bytes"]), ring["triggers"], ring["after_ns"],
                        overwrite=config.get("overwrite", True), warn=_warning), {}
    options = {"split_size": config.get("split_size"), "split_duration_ns": config.get("split_duration_ns"),
               "overwrite": config.get("overwrite", True), "warn": _warning}
    if not config.get("foxglove"):
        return RecordingFile(*args, **options), {}
    from whiztap.sniffer.record.live import LiveRecordingFile, LiveServer, LiveServerError

    try:
        live = LiveServer(*config["foxglove"], warn=_warning)
    except LiveServerError as e:
        raise WriterError(str(e)) from None
    return LiveRecordingFile(live, *args, **options), {"foxglove": live.url}


def _run(config: dict[str, Any]) -> int:
    from whiztap.analyzer.analysis.throughput import tune_gc
    from whiztap.sniffer.record.mirror_record import mirror_recorder
    from whiztap.sniffer.record.recorder import Recorder
    from whiztap.sniffer.record.writer import RecordingWriteError

    tune_gc()  # bulk work on millions of short-lived tuples, like the batch commands
    stop_requested = False

    def on_term(signum: int, frame: object) -> None:
        nonlocal stop_requested
        stop_requested = True

    os.nice(WRITER_NICE)
    _ignore_signals(on_term)
    try:
        file, ready = _recording_file(config)
    except WriterError as e:
        _say({"type": "error", "message": str(e)})
        return EXIT_WRITE_ERROR
    recorder = Recorder(file, keep_secrets=config.get("keep_secrets", False),
                        checksum_rule=config["checksum_rule"], limits=Limits.from_dict(config.get("limits", {})),
                        on_violation=_violation_report if config.get("analyze") else None,
                        middle=config["metadata"].get("middle") == "yes")
    mirror = mirror_recorder(recorder, file, config, _say)  # --mirror: None without
    reported = 0
    verdict = _VerdictReports(recorder)
    try:
        recorder.start(config["start_ns"], **config.get("started", {}))
        _say({"type": "ready", "path": file.current_path, **ready})
        buf = bytearray()
        stop: RecordingStopped | None = None
        while stop is None and not stop_requested:
            if select.select([0], [], [], TICK_S)[0]:
                chunk = os.read(0, 4 << 20)
                if not chunk:
                    break
                buf += chunk
                stop = _apply(recorder, buf, mirror)
            recorder.tick(time.time_ns())
            verdict.report(time.monotonic())
            if mirror is not None:  # what the pairing found, told to the proxy now and then
                mirror.tick(time.monotonic())
            for path in file.finished[reported:]:
                _say({"type": "file", "path": path})
            reported = len(file.finished)
        if stop is None:  # no stop record: the proxy is gone, or SIGTERM came
            stop = RecordingStopped(time.time_ns(), detail="writer terminated" if stop_requested else "proxy gone")
        if mirror is not None:  # every comparison ends before the file does
            mirror.finish(stop.t_ns)
        summary = recorder.stop(stop.t_ns, stop.detail)
    except RecordingWriteError as e:
        _say({"type": "error", "message": str(e)})
        return EXIT_WRITE_ERROR
    from whiztap.sniffer.record.ring import RingFile

    ring = {"ring": file.report()} if isinstance(file, RingFile) else {}  # --ring: the incidents, said at the end
    _say({"type": "summary", **summary.as_dict(), "size": sum(os.path.getsize(p) for p in summary.files), **ring})
    return 0


def main() -> None:
    sys.exit(_run(json.loads(sys.argv[1])))


if __name__ == "__main__":
    main()
