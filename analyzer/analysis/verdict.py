"""The verdict on traffic: one judging path for ``analyze``, the recorder, the TUI and the API.

``verdict_of`` is what ``whiztap analyze`` exits with and what every report's
PASS or FAIL says: the violations left once ignored rules are put aside, by
severity and by side, and whether one is at or above the threshold; with
``fail_on_interventions``, the effects of the proxy's interventions (which
are no side's violation, docs/analyze.md) count toward it too.

``Judge`` gives the same verdict live: it takes traffic events one at a time
(as the proxy tells them, as a recording is read) through the ``Analyzer``
``analyze`` uses, and ``verdict()`` says at any moment what ``analyze`` would
say of the traffic so far.  A connection the proxy stood in the middle of is
judged by each side only once it ends (``sides.py``); until then it is judged
provisionally, as if its traffic ended now, except that requests still within
``--answer-timeout`` are not yet unanswered.  Once ``finish()`` is called the
verdict is exactly ``analyze``'s on the same traffic.

Importing ``Verdict`` and ``verdict_of`` costs no session model (a command's
summary module may import them at ``whiztap --help``); ``Judge`` loads it.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypedDict, Unpack

from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.rules import RULES, Severity
from whiztap.analyzer.protocol.text import plural

if TYPE_CHECKING:  # the session model loads only with a Judge: a Verdict is cheap to import
    from whiztap.analyzer.analysis.analyzer import Analyzer
    from whiztap.analyzer.analysis.facts import Analysis
    from whiztap.analyzer.analysis.sides import Settled
    from whiztap.analyzer.protocol.session import Limits
    from whiztap.analyzer.protocol.stats import LatencyStats
    from whiztap.analyzer.traffic import TrafficEvent

SEVERITIES = (Severity.ERROR, Severity.WARNING, Severity.INFO)


@dataclass(frozen=True, slots=True)
class Verdict:
    """Violations by severity (``error``, ``warning``, ``info``), by side
    (``client``, ``server``) and by rule, ignored rules left out; the effects
    of the interventions by severity; whether the traffic passes, and if not,
    why (``failing``: "violations", "effects", or the reason nothing was judged)."""

    passed: bool
    threshold: Severity
    by_severity: dict[str, int]
    by_side: dict[str, int]
    by_rule: dict[str, int]
    effects_by_severity: dict[str, int]
    connections: int
    failing: str = ""
    nothing_judged: str | None = None

    @property
    def violations(self) -> int:
        return sum(self.by_rule.values())

    @property
    def effects(self) -> int:
        return sum(self.effects_by_severity.values())

    def words(self) -> str:
        """``2 errors, 0 warnings, 1 info``, then the effects when there are any."""
        return counts_words(self.by_severity, self.effects)


def counts_words(by_severity: dict[str, int], effects: int = 0) -> str:
    """``2 errors, 0 warnings, 1 info``, then the effects of the interventions
    when there are any: the counts every verdict line gives."""
    text = (f"{plural(by_severity['error'], 'error')}, {plural(by_severity['warning'], 'warning')}, "
            f"{plural(by_severity['info'], 'info', 'info')}")
    if effects:
        text += f"; {plural(effects, 'effect')} of the interventions"
    return text


class VerdictOptions(TypedDict, total=False):
    """The options of ``verdict_of`` that callers pass along as they got them."""

    threshold: Severity
    ignore: frozenset[str]
    fail_on_interventions: bool
    nothing_judged: str | None
    allow_empty: bool


def verdict_of(rule_sides: Counter, effect_counts: Counter, connections: int, *,
               threshold: Severity = Severity.ERROR, ignore: frozenset[str] = frozenset(),
               fail_on_interventions: bool = False, nothing_judged: str | None = None,
               allow_empty: bool = False) -> Verdict:
    """The verdict on violations counted by (rule, side) and effects counted by
    rule: what every report and ``analyze``'s exit status say."""
    by_severity = {str(s): 0 for s in SEVERITIES}
    by_side = {"client": 0, "server": 0}
    by_rule: Counter[str] = Counter()
    for (rule_id, side), n in rule_sides.items():
        if n and rule_id not in ignore:
            by_severity[str(RULES[rule_id].severity)] += n
            by_side[side] = by_side.get(side, 0) + n
            by_rule[rule_id] += n
    effects = {str(s): 0 for s in SEVERITIES}
    for rule_id, n in effect_counts.items():
        if n and rule_id not in ignore:
            effects[str(RULES[rule_id].severity)] += n
    above = [str(s) for s in SEVERITIES if s >= threshold]
    failing = ""
    if any(by_severity[s] for s in above):
        failing = "violations"
    elif fail_on_interventions and any(effects[s] for s in above):
        failing = "effects"
    elif nothing_judged is not None and not allow_empty:
        failing = nothing_judged
    return Verdict(not failing, threshold, by_severity, by_side, {r: by_rule[r] for r in RULES if by_rule[r]},
                   effects, connections, failing, nothing_judged)


def analysis_verdict(analysis: Analysis, **options: Unpack[VerdictOptions]) -> Verdict:
    """``verdict_of`` an analysis (``options``: as ``verdict_of`` takes them)."""
    return verdict_of(analysis.side_counts, analysis.effect_counts, len(analysis.connections), **options)


class Judge:
    """Traffic events in, ``analyze``'s verdict out, at any moment.

    ``middle``: the traffic is the proxy's in the middle (a recording whose
    metadata says so, or the live proxy with faults, interception or
    injection), so each side is judged by what it did.  The other options are
    ``analyze``'s: ``threshold`` (``--severity-threshold``), ``ignore``
    (``--ignore``), ``fail_on_interventions``.  ``analyzer`` is the
    ``Analyzer`` it feeds, for whoever wants its facts too."""

    def __init__(self, checksum_rule: str = DEFAULT_CHECKSUM_RULE, limits: Limits | None = None, *,
                 middle: bool = False, threshold: Severity = Severity.ERROR, ignore: frozenset[str] = frozenset(),
                 fail_on_interventions: bool = False, name: str = "") -> None:
        from whiztap.analyzer.analysis.analyzer import Analyzer
        from whiztap.analyzer.protocol.session import Limits

        self.analyzer = Analyzer(name, checksum_rule, limits or Limits(), every_event=False, middle=middle)
        self._options: VerdictOptions = {"threshold": threshold, "ignore": ignore,
                                         "fail_on_interventions": fail_on_interventions}
        self._finished: Verdict | None = None

    def receive(self, event: TrafficEvent) -> None:
        self.analyzer.receive(event)

    def verdict(self) -> Verdict:
        """The verdict on the traffic so far (see the module docstring)."""
        if self._finished is not None:
            return self._finished
        analyzer = self.analyzer
        rule_sides = Counter(analyzer.result.side_counts)
        effects = Counter(analyzer.result.effect_counts)
        for _conn, settled in analyzer.open_judgements():
            _add(settled, rule_sides, effects)
        return verdict_of(rule_sides, effects, len(analyzer.summaries), **self._options)

    def finish(self) -> Verdict:
        """The traffic is over: what ``analyze`` says of it, from now on."""
        if self._finished is None:
            self._finished = analysis_verdict(self.analyzer.finish(), **self._options)
        return self._finished

    def latencies(self) -> tuple[dict[str, LatencyStats], dict[str, LatencyStats]]:
        """The server's and the client's latencies by request so far (the
        client's only for connections in the middle; see ``both_latencies``)."""
        return both_latencies(self.analyzer)


def both_latencies(analyzer: Analyzer) -> tuple[dict[str, LatencyStats], dict[str, LatencyStats]]:
    """An analyzer's latencies by request title, open connections included:
    the server's (from the request as it received it to the answer it sent)
    and the client's (from the request as it sent it to the answer as it
    received it).  The two differ only where the proxy stood in the middle;
    the client's are kept only there (empty elsewhere)."""
    server: dict[str, LatencyStats] = {}
    client: dict[str, LatencyStats] = {}
    _merge(server, analyzer.result.latencies)
    _merge(client, analyzer.result.client_latencies)
    judged = analyzer.open_judgements()
    middle = {conn for conn, settled in judged if settled.latencies is not None}
    for conn, session in analyzer.sessions.items():
        if conn not in middle:  # judged as one session: its own latencies
            _merge(server, session.latencies)
    for _conn, settled in judged:
        _merge(server, settled.latencies or {})
        _merge(client, settled.client_latencies or {})
    return server, client


def violations_by_connection(analyzer: Analyzer) -> dict[int, int]:
    """Each connection's violations as ``analyze`` counts them so far: what
    its ended sessions found and, in the middle, an open connection's as if
    its traffic ended now (``Analyzer.open_judgements``); the counts a screen
    lists beside each connection."""
    counts = {conn: sum(summary.violations.values()) for conn, summary in analyzer.summaries.items()}
    for conn, settled in analyzer.open_judgements():
        counts[conn] = counts.get(conn, 0) + len(settled.verdicts) + sum(settled.more.values())
    return counts


def _merge(into: dict[str, LatencyStats], latencies: dict[str, LatencyStats]) -> None:
    from whiztap.analyzer.protocol.stats import LatencyStats

    for title, stats in latencies.items():
        if stats.count:
            into.setdefault(title, LatencyStats()).merge(stats)


def _add(settled: Settled, rule_sides: Counter, effects: Counter) -> None:
    """A provisional judgement's counts, added."""
    for record, _title in settled.verdicts:
        rule_sides[(record.rule_id, record.side)] += 1
    for (rule_id, side, _title), n in settled.more.items():
        rule_sides[(rule_id, side)] += n
    for record in settled.effects:
        effects[record.rule_id] += 1
