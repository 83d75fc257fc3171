"""A flaky sensor: some answers on channel 12 go missing, some read out of range.

Run it in the middle, in front of the simulator (or the robot)::

    whiztap sim --port 7000 --mode vpn &
    whiztap record --listen 6000 --upstream 127.0.0.1:7000 -o flaky.mcap \\
        --script samples/scripts/flaky_sensor.py
    whiztap client 127.0.0.1:6000 'sensor 12'      # a few times

Each answer on channel ``CHANNEL`` (``cr1-12--V--0-ss1``) draws a number from
a generator seeded with ``SEED`` and the connection's id, so a run is
repeatable: below ``DROP`` the answer is dropped (the request times out);
below ``DROP + OUT`` it is replaced by ``cr1-12--5000--0-ss1``, a value no
sensor gives (they read 0 to 1024); otherwise it passes as the robot sent it.
Every other frame passes untouched.  Each change is on ``/interventions``
with the cause ``script flaky_sensor.py``.
"""

from __future__ import annotations

import random
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from whiztap.sniffer.mitm.scripts import Flow

CHANNEL = 12
DROP = 0.25  # the share of answers dropped
OUT = 0.25  # the share of answers replaced by an out-of-range value
OUT_OF_RANGE = 5000
SEED = 2024

_draws: dict[int, random.Random] = {}  # per connection: one connection's answers do not shift another's


def opened(conn: int) -> None:
    _draws[conn] = random.Random(f"{SEED}:{conn}")


def closed(conn: int) -> None:
    _draws.pop(conn, None)


def frame(flow: Flow) -> None:
    if flow.direction != "s2c" or flow.kind != "response" or flow.channel != CHANNEL:
        return
    draw = _draws[flow.conn].random()
    if draw < DROP:
        flow.drop()
    elif draw < DROP + OUT:
        flow.replace(f"cr1-{CHANNEL}--{OUT_OF_RANGE}--0-ss1".encode())
