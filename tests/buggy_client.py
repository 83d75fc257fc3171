"""A small Progwhiz client with planted defects, for ``whiztap probe client`` to catch.

Run as ``python tests/buggy_client.py [--bug NAME] HOST PORT``: it does the
winsock handshake when WHIZTAP_PROBE_PASSWORD is set (VPN otherwise), then
Fetch Configuration Settings, a Sensor Request and Fetch Camera Image, each
awaited, and closes.  Without ``--bug`` it is a correct client: it reads
through the analyzer's framer (so split answers and stray bytes are fine),
gives up after ``WAIT`` seconds of silence, and a server that refuses it or
closes on it is one line on stderr and exit status 1, never a traceback.

Each ``--bug`` plants one defect (``BUGS``, with the case meant to catch it).
"""

from __future__ import annotations

import argparse
import os
import socket
import sys
import time

from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO, SENDCHKPASS

WAIT = 1.0  # seconds a correct client waits for the server
LARGE = 1 << 20
CONFIG, SENSOR, CAMERA = b"rr1-24--0--0-ss1", b"rr1-12--0--0-ss1", b"rr1-29--0--0-ss1"
OUT_OF_RANGE = b"rr1-99--0--0-ss1"

BUGS = {  # name -> (what it does wrong, the case that catches it, the finding)
    "early-commands": ("sends its first command with the password, before 'readytogo'",
                       "slow.answers", "PW-HS-COMMAND-BEFORE-READY"),
    "ignore-failed-validation": ("keeps sending commands after 'Failed Validation'",
                                 "handshake.failed-validation", "PW-HS-AFTER-FAILED"),
    "hang-on-split": ("waits forever for an answer that comes in more than one read",
                      "split.bytes", "PROBE-CLIENT-HANG"),
    "crash-on-large-image": ("raises on a camera image over 1 MiB", "camera.largest", "PROBE-CLIENT-CRASH"),
    "sensor-out-of-range": ("sends a Sensor Request on channel 99", "session.baseline", "PW-RANGE-CHANNEL"),
    "never-closes": ("stays connected after its last answer, forever", "session.baseline", "PROBE-CLIENT-HANG"),
    "no-timeout": ("waits for the server without a time limit", "idle.server", "PROBE-CLIENT-HANG"),
    "crash-on-close": ("raises when the server closes the connection", "close.mid-session", "PROBE-CLIENT-CRASH"),
    "crash-on-garbage": ("raises on bytes that form no item", "garbage.before-answer", "PROBE-CLIENT-CRASH"),
}


class ServerGone(Exception):
    """The server closed the connection or said nothing in time: a correct client says so and exits 1."""


class Connection:
    def __init__(self, sock: socket.socket, bug: str | None) -> None:
        self.sock = sock
        self.bug = bug
        self.framer = Framer()
        self.items: list[Item] = []
        sock.settimeout(None if bug in ("no-timeout", "hang-on-split") else WAIT)

    def next_item(self) -> Item:
        while not self.items:
            try:
                data = self.sock.recv(65536)
            except TimeoutError:
                raise ServerGone(f"no answer within {WAIT:g} s") from None
            if not data:
                if self.bug == "crash-on-close":
                    raise ConnectionError("the server went away")  # uncaught: the planted crash
                raise ServerGone("the server closed the connection")
            self.items.extend(i for i in self.framer.feed(data, time.monotonic_ns()) if i.kind is not ItemKind.EOL)
        item = self.items.pop(0)
        if item.kind is ItemKind.UNFRAMED and self.bug == "crash-on-garbage":
            raise ValueError(f"cannot parse {item.raw!r}")
        return item

    def next_answer(self, image: bool = False) -> Item:
        """The next item that is no stray bytes (a correct client skips them)."""
        if self.bug == "hang-on-split" and not image:
            return self._whole_read()
        while (item := self.next_item()).kind is ItemKind.UNFRAMED:
            pass
        return item

    def _whole_read(self) -> Item:
        """The planted defect: an answer must come in one read; a read that
        holds only part of one leaves the client waiting for ever."""
        framer = Framer()
        while True:
            data = self.sock.recv(65536)
            if not data:
                raise ServerGone("the server closed the connection")
            whole = [i for i in framer.feed(data, time.monotonic_ns()) if i.kind is not ItemKind.EOL]
            if whole and not framer.buffered:
                return whole[0]
            while True:  # a part of an answer: never understood, never given up on
                time.sleep(60)


def handshake(conn: Connection, password: bytes, first: bytes) -> None:
    item = conn.next_answer()
    if item.raw != SENDCHKPASS:
        raise ServerGone(f"expected sendchkpass, got {item.raw[:40]!r}")
    conn.sock.sendall(password + (first if conn.bug == "early-commands" else b""))
    verdict = conn.next_answer().raw
    if verdict == FAILED_VALIDATION:
        if conn.bug == "ignore-failed-validation":
            for frame in (CONFIG, SENSOR):
                conn.sock.sendall(frame)
                time.sleep(0.05)
        raise ServerGone("Failed Validation")
    if verdict != READYTOGO:
        raise ServerGone(f"expected readytogo, got {verdict[:40]!r}")


def session(conn: Connection, password: str | None) -> None:
    requests = [CONFIG, OUT_OF_RANGE if conn.bug == "sensor-out-of-range" else SENSOR, CAMERA]
    if password is not None:
        handshake(conn, password.encode(), requests[0])
        if conn.bug == "early-commands":
            requests = requests[1:]
            conn.next_answer()
    for frame in requests:
        conn.sock.sendall(frame)
        if frame == OUT_OF_RANGE:
            continue  # no answer comes to a request the server ignores
        answer = conn.next_answer(image=frame == CAMERA)
        if frame == CAMERA and len(answer.raw) > LARGE and conn.bug == "crash-on-large-image":
            raise MemoryError(f"image of {len(answer.raw)} bytes")  # uncaught: the planted crash
    if conn.bug == "never-closes":
        while True:
            time.sleep(60)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bug", choices=sorted(BUGS))
    parser.add_argument("host")
    parser.add_argument("port", type=int)
    args = parser.parse_args()
    password = os.environ.get("WHIZTAP_PROBE_PASSWORD")
    with socket.create_connection((args.host, args.port), timeout=WAIT) as sock:
        try:
            session(Connection(sock, args.bug), password)
        except ServerGone as e:
            print(f"buggy_client: {e}", file=sys.stderr)
            return 1
        except OSError as e:
            if args.bug == "crash-on-close":
                raise
            print(f"buggy_client: {e}", file=sys.stderr)
            return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
