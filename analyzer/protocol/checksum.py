"""The Set Configuration Settings checksum, as a choice among candidate rules.

The spec gives one example (Dev# 12 on ports 0-5, all servos, checksum 72) and no
formula.  The plain sum of every payload byte is 87, so that is not it.  Each rule
below reproduces the example; the session uses one (the default unless told),
and reports name every rule an observed checksum satisfies, so a user with a
real server can see which one it implements.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

from whiztap.analyzer.protocol.messages import SetConfigEntry, SetConfiguration
from whiztap.analyzer.protocol.rules import Violation


@dataclass(frozen=True, slots=True)
class ChecksumRule:
    name: str
    description: str
    compute: Callable[[Iterable[SetConfigEntry]], int]


CHECKSUM_RULES: dict[str, ChecksumRule] = {
    r.name: r
    for r in (
        ChecksumRule("dev-sum", "sum of the Dev# bytes, modulo 256",
                     lambda entries: sum(e.device for e in entries) % 256),
        ChecksumRule("dev-unit-sum", "sum of the Dev# and unit type bytes, modulo 256",
                     lambda entries: sum(e.device + e.unit_type for e in entries) % 256),
        ChecksumRule("dev-sum-7bit", "sum of the Dev# bytes, modulo 128",
                     lambda entries: sum(e.device for e in entries) % 128),
    )
}
DEFAULT_CHECKSUM_RULE = "dev-sum"


def get_rule(name: str) -> ChecksumRule:
    try:
        return CHECKSUM_RULES[name]
    except KeyError:
        known = ", ".join(CHECKSUM_RULES)
        raise ValueError(f"unknown checksum rule {name!r}: expected one of {known}") from None


def satisfied_rules(entries: tuple[SetConfigEntry, ...], checksum: int) -> tuple[str, ...]:
    """Names of every candidate rule under which ``checksum`` is right."""
    return tuple(name for name, rule in CHECKSUM_RULES.items() if rule.compute(entries) == checksum)


def checksum_violation(message: SetConfiguration, rule: ChecksumRule) -> Violation | None:
    """PW-SETCFG-CHECKSUM when the message's checksum is not what ``rule`` makes
    of its entries (None: it is), one wording for the session and a frame checked
    on its own (analyzer/protocol/frame_text.py)."""
    expected = rule.compute(message.entries)
    if expected == message.checksum:
        return None
    return Violation("PW-SETCFG-CHECKSUM", f"expected {expected} ({rule.name}), got {message.checksum}")
