"""What a probe run says: one ``CaseResult`` per case, gathered in a ``ProbeReport``.

Shared by ``probe server`` (whiztap plays the client) and ``probe client``
(whiztap plays the server) so both print the same shapes: the JSON one
(``ProbeReport.to_json``) is a documented interface CI jobs read, so its keys
only ever grow.  Exit statuses follow from the report: 0 when no case failed,
1 when one did (``exit_status``); 2 is for a run that could not happen at all,
which raises before there is a report.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any


class Outcome(StrEnum):
    """A case's verdict.  ``SKIP`` is for a case whose expectation the spec
    leaves open or that the target cannot take (its reason says which): never
    a guess reported as a failure."""

    PASS = "pass"
    FAIL = "fail"
    SKIP = "skip"


@dataclass(frozen=True, slots=True)
class Finding:
    """One thing a case found wrong: a whiztap rule id (``PW-...``) or a
    probe's own (``PROBE-...``: no answer, a close, a hang), and the detail."""

    rule: str
    detail: str


@dataclass(frozen=True, slots=True)
class CaseResult:
    """A case as it ran.  ``spec``: the spec section it comes from; ``reason``:
    why it was skipped, or a note on a pass; ``conn``: its connection's
    number in the ``--record`` recording (None when not recorded);
    ``seconds``: how long it took."""

    id: str
    title: str
    spec: str
    verdict: Outcome
    findings: tuple[Finding, ...] = ()
    reason: str = ""
    conn: int | None = None
    seconds: float = 0.0

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"id": self.id, "title": self.title, "spec": self.spec, "verdict": str(self.verdict),
                               "violations": [{"rule": f.rule, "detail": f.detail} for f in self.findings]}
        if self.reason:
            out["reason"] = self.reason
        if self.conn is not None:
            out["conn"] = self.conn
        return out


@dataclass(slots=True)
class ProbeReport:
    """Every case of one run against ``target`` (``HOST:PORT``, or the client's
    command line), whiztap playing ``role``'s peer: "server" when the server is
    probed, "client" when the client is.  ``recording``: the ``--record`` file."""

    target: str
    role: str
    cases: list[CaseResult] = field(default_factory=list)
    seed: int = 0
    mode: str = ""  # the handshake found or played: "winsock" or "vpn"
    recording: str = ""
    seconds: float = 0.0

    def count(self, outcome: Outcome) -> int:
        return sum(1 for case in self.cases if case.verdict is outcome)

    @property
    def passed(self) -> int:
        return self.count(Outcome.PASS)

    @property
    def failed(self) -> int:
        return self.count(Outcome.FAIL)

    @property
    def skipped(self) -> int:
        return self.count(Outcome.SKIP)

    @property
    def exit_status(self) -> int:
        return 1 if self.failed else 0

    def by_section(self) -> dict[str, list[CaseResult]]:
        """The cases grouped by spec section, sections in the order first met."""
        sections: dict[str, list[CaseResult]] = {}
        for case in self.cases:
            sections.setdefault(case.spec, []).append(case)
        return sections

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {"target": self.target, "role": self.role, "mode": self.mode, "seed": self.seed,
                               "cases": [case.to_json() for case in self.cases],
                               "passed": self.passed, "failed": self.failed, "skipped": self.skipped}
        if self.recording:
            out["recording"] = self.recording
        return out


def findings(pairs: Iterable[tuple[str, str]]) -> tuple[Finding, ...]:
    """(rule, detail) pairs as findings, in order."""
    return tuple(Finding(rule, detail) for rule, detail in pairs)
