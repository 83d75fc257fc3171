"""A slow servo controller: answers to Servo Position Requests come late.

Run it in the middle, in front of the simulator (or the robot)::

    whiztap sim --port 7000 --mode vpn &
    whiztap record --listen 6000 --upstream 127.0.0.1:7000 -o late.mcap \\
        --script samples/scripts/late_servo.py
    whiztap client 127.0.0.1:6000 'servo 0'        # answers after 300 ms

An answer does not say what it answers (``cr1-0--V--0-ss1`` answers a Servo
Position Request or a Sensor Request alike), so the script notes each Servo
Position Request the client sends, per connection and channel, and delays
the next answer on that channel by ``DELAY_S`` seconds.  Everything behind a
delayed answer waits too (the proxy never reorders a direction); every other
frame passes untouched.  Each delay is on ``/interventions`` with the cause
``script late_servo.py``.
"""

from __future__ import annotations

from collections import Counter
from typing import TYPE_CHECKING

from whiztap.analyzer.protocol.messages import ServoPositionRequest

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.scripts import Flow

DELAY_S = 0.3

_asked: dict[int, Counter[int]] = {}  # per connection: Servo Position Requests not answered yet, by channel


def opened(conn: int) -> None:
    _asked[conn] = Counter()


def closed(conn: int) -> None:
    _asked.pop(conn, None)


def frame(flow: Flow) -> None:
    asked = _asked[flow.conn]
    if flow.direction == "c2s" and isinstance(flow.message, ServoPositionRequest):
        asked[flow.channel] += 1
    elif flow.direction == "s2c" and flow.kind == "response" and asked[flow.channel] > 0:
        asked[flow.channel] -= 1
        flow.delay(DELAY_S)
