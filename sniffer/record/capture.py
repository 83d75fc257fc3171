"""``whiztap capture``: recordings from pcap/pcapng files and live interfaces.

Both paths stream: a file is read packet by packet with Scapy's raw readers
(no dissection, never the whole file in memory), a live interface through a
raw socket with a BPF filter.  Frames are decoded by ``whiztap.sniffer.record.tcpreasm``,
reassembled per connection and direction, and fed to the same Recorder as
``whiztap record`` writes with, so a capture and a proxy recording of one
session hold the same frames.
"""

from __future__ import annotations

import select
import signal
import socket
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.session import Limits
from whiztap.sniffer.record.detect import ContentDetector
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.tcpreasm import DLT_EN10MB, DLT_RAW, Reassembler, parse_frame
from whiztap.sniffer.record.writer import STOP_SIGNALS, RecordingFile, RecordingWriteError

if TYPE_CHECKING:
    from scapy.supersocket import SuperSocket

TICK_EVERY = 2048  # packets between flush/rotation checks when importing
SNAP = 1 << 18  # larger than any frame on a 64 KiB-MTU loopback
DRAIN_MAX = 100_000  # packets read after a stop, at most


class CaptureError(WhiztapError):
    """A capture could not run; one line for the user."""


@dataclass(frozen=True)
class CaptureSettings:
    port: int | None  # None: find Progwhiz conversations on any port by their content
    output: str
    split_size: int | None = None
    split_duration: float | None = None
    keep_secrets: bool = False
    checksum_rule: str = "dev-sum"
    limits: Limits = Limits()
    overwrite: bool = True  # as RecordSettings.overwrite


def _recorder(settings: CaptureSettings, source: str, start_ns: int, **extra: object) -> Recorder:
    from whiztap.sniffer.record.metadata import base_metadata

    metadata = base_metadata(source, settings.keep_secrets, settings.checksum_rule, start_ns, None,
                             server_port=settings.port, split_size=settings.split_size,
                             split_duration=settings.split_duration, **extra)
    split_ns = int(settings.split_duration * 1e9) if settings.split_duration else None
    file = RecordingFile(settings.output, metadata, split_size=settings.split_size, split_duration_ns=split_ns,
                         overwrite=settings.overwrite)
    return Recorder(file, keep_secrets=settings.keep_secrets, checksum_rule=settings.checksum_rule,
                    limits=settings.limits)


def _follower(settings: CaptureSettings, recorder: Recorder) -> Reassembler | ContentDetector:
    """What turns TCP segments into the recorder's traffic: a reassembler for
    the server's port, or, without one, for every Progwhiz conversation found."""
    if settings.port is None:
        return ContentDetector(recorder)
    return Reassembler(settings.port, recorder)


def _what_is_captured(settings: CaptureSettings) -> str:
    """The traffic a capture records, in words."""
    return "Progwhiz conversations on any TCP port" if settings.port is None else f"tcp port {settings.port}"


def _summary(recorder: Recorder, t_ns: int, detail: str) -> dict:
    import os

    summary = recorder.stop(t_ns, detail).as_dict()
    summary["size"] = sum(os.path.getsize(p) for p in summary["files"])
    return summary


def _timestamp(meta: Any, nano: bool) -> int:
    """A packet's time in ns; ``meta``: scapy's PacketMetadata, or PacketMetadataNg
    (a pcapng file's), told apart by their fields."""
    if hasattr(meta, "tshigh"):
        return ((meta.tshigh << 32) | meta.tslow) * 1_000_000_000 // meta.tsresol
    return meta.sec * 1_000_000_000 + meta.usec * (1 if nano else 1000)


def import_pcap(path: str, settings: CaptureSettings, progress: Callable[[int], None] | None = None) -> dict:
    """Record the traffic to ``settings.port`` (None: every Progwhiz
    conversation) in a pcap or pcapng file; the summary.  ``progress`` is told
    how far into the file the reading is, now and then and at the end."""
    from scapy.error import Scapy_Exception
    from scapy.utils import RawPcapReader

    try:
        reader = RawPcapReader(path)
    except FileNotFoundError:
        raise CaptureError(f"cannot read {path}: No such file or directory") from None
    except OSError as e:
        raise CaptureError(f"cannot read {path}: {e.strerror}") from None
    except Scapy_Exception as e:
        raise CaptureError(f"{path} is not a pcap or pcapng file ({e})") from None
    nano = bool(getattr(reader, "nano", False))
    recorder = None
    t = 0
    try:
        with reader:
            count = 0
            while True:
                try:
                    frame, meta = reader._read_packet(SNAP)  # the public iterator cuts at 64 KiB
                except EOFError:
                    break
                t = _timestamp(meta, nano)
                if recorder is None:
                    recorder = _recorder(settings, "pcap", t, pcap=path)
                    recorder.start(t, detail=f"import of {path}")
                    reassembler = _follower(settings, recorder)
                linktype = getattr(meta, "linktype", None)
                segment = parse_frame(reader.linktype if linktype is None else linktype, frame, t)
                if segment is not None:
                    reassembler.segment(segment)
                count += 1
                if count % TICK_EVERY == 0:
                    recorder.tick(t)
                    if progress is not None:
                        progress(reader.f.tell())
            if progress is not None:
                progress(reader.f.tell())
        if recorder is None:
            recorder = _recorder(settings, "pcap", time.time_ns(), pcap=path)
            recorder.start(time.time_ns(), detail=f"import of {path} (no packets)")
        else:
            reassembler.finish(t)
        return _summary(recorder, t, "end of capture file")
    except RecordingWriteError as e:
        raise CaptureError(str(e)) from None


def _live_linktype(frame: bytes) -> int:
    """PF_PACKET frames carry an Ethernet header on Ethernet and loopback
    interfaces and none on tunnels; Scapy cannot always say which (it calls lo's
    frames Raw), so look: an IP ethertype at offset 12 means Ethernet."""
    if len(frame) >= 14 and frame[12:14] in (b"\x08\x00", b"\x86\xdd", b"\x81\x00"):
        return DLT_EN10MB
    return DLT_RAW


def _open_live(iface: str, port: int | None) -> SuperSocket:
    import importlib
    import logging

    importlib.import_module("scapy.arch")  # sets conf.L2listen for this platform
    from scapy.config import conf
    from scapy.error import Scapy_Exception

    logging.getLogger("scapy.runtime").setLevel(logging.ERROR)  # no "unable to guess type" noise

    try:
        return conf.L2listen(iface=iface, filter="tcp" if port is None else f"tcp port {port}")
    except PermissionError:
        raise CaptureError(
            f"live capture on {iface} needs root or the CAP_NET_RAW capability "
            "(run as root, or grant it: sudo setcap cap_net_raw+eip \"$(readlink -f $(which python3))\"); "
            "or capture with tcpdump and import with --pcap") from None
    except OSError as e:
        raise CaptureError(f"cannot capture on {iface}: {e.strerror or e}") from None
    except Scapy_Exception as e:
        raise CaptureError(f"cannot capture on {iface}: {e}") from None
    except ValueError:  # scapy's "Interface 'x' not found !"
        names = ", ".join(sorted(n for _, n in socket.if_nameindex()))
        raise CaptureError(f"cannot capture on {iface}: no such interface (this machine has: {names})") from None


def capture_live(iface: str, settings: CaptureSettings, *, count: int | None = None,
                 timeout: float | None = None, announce: Callable[[str], None] | None = None) -> dict:
    """Record traffic to ``settings.port`` (None: every Progwhiz conversation)
    seen on ``iface`` until Ctrl-C, SIGTERM, SIGHUP, ``count`` packets or
    ``timeout`` seconds; the summary.

    The signals (a closed terminal sends SIGHUP) only set a flag, so a packet is
    never half processed; the packets the kernel has already queued for the
    socket are still recorded."""
    sock = _open_live(iface, settings.port)
    start = time.time_ns()
    recorder = _recorder(settings, "live", start, iface=iface)
    stop = False

    def on_signal(signum: int, frame: object) -> None:
        nonlocal stop
        stop = True

    previous = {sig: signal.signal(sig, on_signal) for sig in STOP_SIGNALS}
    t = start
    try:
        recorder.start(start, detail=f"live capture on {iface}, {_what_is_captured(settings)}")
        reassembler = _follower(settings, recorder)
        if announce is not None:
            announce(f"capturing {_what_is_captured(settings)} on {iface} into {settings.output} (Ctrl-C to stop)")
        seen = 0
        deadline = None if timeout is None else time.monotonic() + timeout
        while not stop and (count is None or seen < count) and (deadline is None or time.monotonic() < deadline):
            if select.select([sock], [], [], 0.1)[0]:
                t, seen = _live_packet(sock, reassembler, t, seen)
            recorder.tick(time.time_ns())
        for _ in range(DRAIN_MAX):  # what was captured before the stop
            if (count is not None and seen >= count) or not select.select([sock], [], [], 0)[0]:
                break
            t, seen = _live_packet(sock, reassembler, t, seen)
        t = max(t, time.time_ns())
        reassembler.finish(t)
        return _summary(recorder, t, "capture stopped")
    except RecordingWriteError as e:
        raise CaptureError(str(e)) from None
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sock.close()


def _live_packet(sock: SuperSocket, reassembler: Reassembler | ContentDetector, t: int,
                 seen: int) -> tuple[int, int]:
    """Read one packet; the time of the latest, and how many TCP segments so far."""
    _cls, frame, ts = sock.recv_raw(SNAP)
    if frame is None:
        return t, seen
    t = int(ts * 1e9) if ts else time.time_ns()
    segment = parse_frame(_live_linktype(frame), frame, t)
    if segment is None:
        return t, seen
    reassembler.segment(segment)
    return t, seen + 1
