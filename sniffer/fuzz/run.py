"""The fuzzing loop: mutate, execute, keep what is new, shrink and write what fails.

Deterministic for a seed: one ``random.Random(seed)`` draws every mutation and
corpus choice, executions are counted, and nothing else is random, so the same
seed against a server that behaves the same makes the same executions and the
same findings.  The time budget only stops the loop (and shrinking); with
``executions`` the loop stops at that count whatever the time.

Memory is bounded: the corpus (``analyzer.fuzz.corpus``), at most
``MAX_FINDINGS`` findings (one per kind and rule: the same failure found again
is counted, not kept) and at most ``MAX_RECORDED_SEEDS`` seed sessions from
recordings.
"""

from __future__ import annotations

import random
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from whiztap.analyzer.fuzz.corpus import Corpus
from whiztap.analyzer.fuzz.grammar import Knowledge, Session, from_recording, generate, prelude
from whiztap.analyzer.fuzz.judge import Verdict
from whiztap.analyzer.fuzz.mutate import mutate
from whiztap.analyzer.fuzz.shrink import shrink
from whiztap.sniffer.fuzz.execute import Outcome, alive, checked, discover
from whiztap.sniffer.fuzz.server import Server

GENERATED_SEEDS = 8  # sessions generated from the tables to start the corpus
MAX_RECORDED_SEEDS = 64  # connections taken from --from recordings
MAX_FINDINGS = 20
SHRINK_LIMIT = 400  # executions one shrink may use


@dataclass(frozen=True)
class FuzzOptions:
    address: tuple[str, int]
    password: bytes = b""
    seed: int = 0
    budget: float = 60.0  # seconds; stops the loop, never decides what it does
    executions: int | None = None  # stop after this many (tests: deterministic, not time-bound)
    deadline: float = 1.0  # seconds an owed answer may take
    recorded: tuple[tuple[tuple[str, bytes], ...], ...] = ()  # --from: each connection's client items


@dataclass
class Found:
    """One finding: its verdict, the session that shows it (shrunk unless
    ``shrunk`` is False), and the execution that found it."""

    number: int
    verdict: Verdict
    session: Session
    execution: int
    shrunk: bool = True
    recording: str = ""
    test: str = ""

    @property
    def id(self) -> str:
        return f"finding-{self.number}"

    def to_json(self) -> dict[str, Any]:
        return {"id": self.id, "kind": self.verdict.kind, "frames": len(self.session), "recording": self.recording,
                "test": self.test, "rule": self.verdict.rule, "detail": self.verdict.detail,
                "execution": self.execution, "shrunk": self.shrunk,
                "session": [frame.shown() for frame in self.session]}


@dataclass
class FuzzReport:
    target: str
    seed: int
    mode: str = ""
    findings: list[Found] = field(default_factory=list)
    executions: int = 0
    shrink_executions: int = 0
    seconds: float = 0.0
    stopped: str = ""  # why the loop ended

    def to_json(self) -> dict[str, Any]:
        return {"target": self.target, "seed": self.seed, "mode": self.mode,
                "findings": [f.to_json() for f in self.findings], "executions": self.executions,
                "shrink_executions": self.shrink_executions, "stopped": self.stopped}


Writer = Callable[[Found, Knowledge], "Any"]  # writes a finding's files (a coroutine function)


class Fuzzer:
    """One run of ``whiztap fuzz server``; ``write`` saves each finding as it
    is made, ``progress`` is told after every execution."""

    def __init__(self, options: FuzzOptions, server: Server, write: Writer,
                 progress: Callable[[FuzzReport], None] | None = None) -> None:
        self.options = options
        self.server = server
        self.write = write
        self.progress = progress
        host, port = options.address
        self.report = FuzzReport(f"{host}:{port}", options.seed)
        self.knowledge = Knowledge()
        self._started = 0.0

    def _out_of_time(self) -> bool:
        return time.monotonic() - self._started > self.options.budget

    async def run(self) -> FuzzReport:
        self._started = time.monotonic()
        await self.server.start()
        try:
            await self._loop()
        finally:
            await self.server.stop()
            self.report.seconds = time.monotonic() - self._started
        return self.report

    async def _loop(self) -> None:
        o, report = self.options, self.report
        self.knowledge, first = await discover(o.address, o.password, o.deadline)
        report.mode = str(self.knowledge.mode)
        seen: set[tuple[str, str]] = set()
        if first is not None:  # a breach while learning: the handshake and the configuration show it
            seen.add(first.signature)
            if not await self._found(first, prelude(self.knowledge), False):
                return
        rng = random.Random(o.seed)
        seeds = [generate(rng, self.knowledge) for _ in range(GENERATED_SEEDS)]
        seeds += [from_recording(items, self.knowledge) for items in o.recorded[:MAX_RECORDED_SEEDS]]
        corpus = Corpus(seeds)
        while True:
            if o.executions is not None and report.executions >= o.executions:
                report.stopped = f"{o.executions} executions"
                return
            if self._out_of_time():
                report.stopped = f"the {o.budget:g} s budget"
                return
            base, donor = corpus.pick(rng)
            session, _ = mutate(rng, base, self.knowledge, donor)
            outcome, down = await self._execute(session)
            report.executions += 1
            corpus.consider(rng, session, outcome.behaviour)
            verdict = outcome.verdict
            if verdict is not None and verdict.signature not in seen:
                seen.add(verdict.signature)
                if not await self._found(verdict, session, down):
                    return
            elif down and not await self.server.restart():
                report.stopped = "the server stopped accepting connections"
                return
            if self.progress is not None:
                self.progress(report)
            if len(report.findings) >= MAX_FINDINGS:
                report.stopped = f"{MAX_FINDINGS} findings"
                return

    async def _execute(self, session: Session) -> tuple[Outcome, bool]:
        o = self.options
        return await checked(o.address, session, self.knowledge, o.password, o.deadline)

    async def _found(self, verdict: Verdict, session: Session, down: bool) -> bool:
        """Shrink, record and write a new finding; False when the run must end
        (the server is down and cannot be restarted)."""
        report = self.report
        found = Found(len(report.findings) + 1, verdict, session, report.executions, shrunk=False)
        keep_going = not down or await self.server.restart()
        if keep_going:
            found.session, found.shrunk = await self._shrink(session, verdict)
        else:
            report.stopped = "the server stopped accepting connections"
        report.findings.append(found)
        await self.write(found, self.knowledge)
        if keep_going and not await self._back_up():
            report.stopped = "the server stopped accepting connections"
            return False
        return keep_going

    async def _back_up(self) -> bool:
        """After writing (which ran the finding again): the server restarted if it is down."""
        o = self.options
        return await alive(o.address, self.knowledge, o.password, o.deadline) or await self.server.restart()

    async def _shrink(self, session: Session, verdict: Verdict) -> tuple[Session, bool]:
        """The smallest session found that fails the same way, within the
        budget and ``SHRINK_LIMIT`` executions; whether shrinking finished."""
        steps = shrink(session)
        best, used = session, 0
        try:
            candidate = next(steps)
            while True:
                if used >= SHRINK_LIMIT or self._out_of_time():
                    return best, False
                outcome, down = await self._execute(candidate)
                used += 1
                self.report.shrink_executions += 1
                if down and not await self.server.restart():
                    return best, False
                same = outcome.verdict is not None and outcome.verdict.signature == verdict.signature
                if same:
                    best = candidate
                candidate = steps.send(same)
        except StopIteration as done:
            return done.value, True

