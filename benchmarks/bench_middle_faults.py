"""What a frame costs in the middle as faults pile up (docs/benchmarks.md).

One connection's ``MiddleCore`` driven in-process through a ``Controller``
(no socket, a shell that only lets the receivers take what is written), fed
reads of 100 Sensor/Servo Responses (``s2c``), CPU time
(``time.process_time``) best of three; N faults ``drop dir:WAY ch:90..98
every:K`` in force.  On ``dir:c2s`` no answer is ever offered to them (the
route by direction and kind, ``Stages``), so their count must not matter; on
``dir:s2c`` each answer is offered to each (their ``ch:`` refuses it), so the
cost grows with their count up to the cap of 256 faults in force.

Prints figures; asserts nothing (timings belong here, not in tests).
"""

from __future__ import annotations

import os
import time

from whiztap.analyzer.mitm.commands import Command
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.mitm.controller import Controller

FRAMES = int(os.environ.get("WHIZTAP_BENCH_MIDDLE_FRAMES", 100_000))
PER_READ = 100
REPEATS = 3
COUNTS = (1, 16, 64, 255)
T0 = 1_700_000_000_000_000_000


class _Taker:
    """The shell: carries out nothing, and the receivers take all (so no lane stops)."""

    client_addr = "127.0.0.1:40000"

    def __init__(self) -> None:
        self.core = None

    def run(self, commands: list[Command]) -> None:
        core = self.core
        if core is not None:
            for direction in (Direction.C2S, Direction.S2C):
                if core.blocked(direction):
                    self.run(core.writable(direction, T0))


def frames_per_second(way: str, faults: int) -> float:
    """Best of ``REPEATS``: answers a CPU second through one core with ``faults`` in force."""
    controller = Controller(seed=0, report=lambda line: None)
    controller.attach(lambda: T0, lambda event: None)
    for n in range(faults):
        controller.add_fault(f"drop dir:{way} ch:{90 + n % 9} every:{2 + n % 7}")
    shell = _Taker()
    core, commands = controller.open(1, shell)
    shell.core = core
    shell.run(commands)
    for direction in (Direction.C2S, Direction.S2C):
        shell.run(core.ready(direction, T0))
    read = b"".join(encode(m.ChannelResponse(12 + i % 12, i % 1025)) for i in range(PER_READ))
    reads = max(1, FRAMES // PER_READ)
    best = float("inf")
    for _ in range(REPEATS):
        start = time.process_time()
        for i in range(reads):
            shell.run(core.received(Direction.S2C, read, T0 + i))
        best = min(best, time.process_time() - start)
    return reads * PER_READ / best if best else float("inf")


def main() -> None:
    print(f"== the middle as faults pile up: {FRAMES:,} answers, best of {REPEATS}, CPU time ==")
    for way, why in (("c2s", "never offered an answer"), ("s2c", "offered each answer, refused by ch:")):
        for count in COUNTS:
            print(f"FRAMES/S  {count:>3} faults on dir:{way} ({why}): {frames_per_second(way, count):>12,.0f}")


if __name__ == "__main__":
    main()
