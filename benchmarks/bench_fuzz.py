"""`whiztap fuzz server` against the simulator, side by side with a naive fuzzer.

In one run, in this process, against the real simulator over loopback
(restarted after each crash, as ``--run`` would):

- executions per second against the clean simulator, for the spec-aware
  fuzzer and for a naive one that logs in and then sends random bytes (1 to 64,
  one write), judged by the same execution code;
- executions and seconds to the first finding for each planted crash bug
  (split-crash, crash-on-frame), median of ``SEEDS`` seeds, for both (the naive
  one stopped at ``NAIVE_CAP`` executions: ">" marks a median it never reached);
- the shrunk findings' size in frames.
"""

from __future__ import annotations

import asyncio
import random
import socket
import statistics
import time

from whiztap.analyzer.fuzz.grammar import Frame, Knowledge, Session
from whiztap.analyzer.fuzz.judge import Verdict
from whiztap.sniffer.fuzz.execute import checked, learn
from whiztap.sniffer.fuzz.run import Found, FuzzOptions, Fuzzer
from whiztap.sniffer.fuzz.server import InProcess
from whiztap.sniffer.sim.simulator import Simulator

PASSWORD = b"bench-pw"
SEEDS = 5
SPEED_EXECUTIONS = 300
AWARE_CAP = 2000
NAIVE_CAP = 1000
CRASH_BUGS = ("split-crash", "crash-on-frame")


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _server(port: int, bugs: tuple[str, ...]) -> InProcess:
    async def start() -> Simulator:
        sim = Simulator(port=port, password=PASSWORD, bugs=bugs)
        await sim.start()
        return sim
    return InProcess(start)


class _Timed(Fuzzer):
    """The fuzzer, noting when its first finding came (before shrinking it),
    and ending the run once it is shrunk."""

    first: tuple[int, float] | None = None

    async def _found(self, verdict: Verdict, session: Session, down: bool) -> bool:
        self.first = (self.report.executions, time.monotonic() - self._started)
        await super()._found(verdict, session, down)
        return False


async def _aware(bugs: tuple[str, ...], seed: int, executions: int) -> tuple[_Timed, float]:
    port = _port()
    found: list[Found] = []

    async def keep(f: Found, k: Knowledge) -> None:
        found.append(f)

    fuzzer = _Timed(FuzzOptions(("127.0.0.1", port), PASSWORD, seed, 600, executions), _server(port, bugs), keep)
    started = time.monotonic()
    await fuzzer.run()
    return fuzzer, time.monotonic() - started


async def _naive(bugs: tuple[str, ...], seed: int, cap: int) -> tuple[int, float, int | None]:
    """Executions run, seconds, and the execution of the first crash (None: none)."""
    port = _port()
    address = ("127.0.0.1", port)
    server = _server(port, bugs)
    await server.start()
    rng = random.Random(seed)
    started = time.monotonic()
    try:
        knowledge = await learn(address, PASSWORD, 1.0)
        for n in range(1, cap + 1):
            junk = bytes(rng.randrange(256) for _ in range(rng.randint(1, 64)))
            outcome, down = await checked(address, (Frame(secret="password"), Frame(junk)), knowledge, PASSWORD, 1.0)
            if down or (outcome.verdict is not None and outcome.verdict.kind == "crash"):
                return n, time.monotonic() - started, n
    finally:
        await server.stop()
    return cap, time.monotonic() - started, None


def _median(values: list[float]) -> float:
    return statistics.median(values)


async def _bench() -> None:
    aware, aware_s = await _aware((), 1, SPEED_EXECUTIONS)
    naive_n, naive_s, _ = await _naive((), 1, SPEED_EXECUTIONS)
    print(f"{'against the clean simulator':<34} {'spec-aware':>14} {'naive':>14}")
    print(f"{'executions per second':<34} {aware.report.executions / aware_s:>14.0f} {naive_n / naive_s:>14.0f}")
    print(f"{'findings':<34} {len(aware.report.findings):>14} {'-':>14}")
    print()
    print(f"first finding, median of {SEEDS} seeds   executions (aware / naive)   seconds (aware / naive)"
          "   shrunk frames")
    for bug in CRASH_BUGS:
        a_runs, a_secs, n_runs, n_secs, frames = [], [], [], [], []
        for seed in range(SEEDS):
            fuzzer, _ = await _aware((bug,), seed, AWARE_CAP)
            if fuzzer.first is not None:
                a_runs.append(fuzzer.first[0])
                a_secs.append(fuzzer.first[1])
                frames.append(len(fuzzer.report.findings[0].session))
            else:
                a_runs.append(AWARE_CAP)
            runs, secs, hit = await _naive((bug,), seed, NAIVE_CAP)
            n_runs.append(runs if hit is not None else NAIVE_CAP + 1)
            n_secs.append(secs)
        naive_mark = ">" if _median(n_runs) > NAIVE_CAP else ""
        naive_runs = f"{naive_mark}{min(_median(n_runs), NAIVE_CAP):.0f}"
        print(f"{bug:<34} {_median(a_runs):>10.0f} / {naive_runs:<10} {_median(a_secs) if a_secs else 0:>10.2f} / "
              f"{naive_mark}{_median(n_secs):<8.2f} {frames}")


def main() -> None:
    print("whiztap fuzz server vs naive random bytes (in-process simulator, loopback)")
    asyncio.run(_bench())


if __name__ == "__main__":
    main()
