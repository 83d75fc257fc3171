"""A frame a person types (to inject, or as the edit of a held frame), judged as it is typed.

The reading is the Controller's own (``frame_from_text``: escaped text or the
console's words) and so is the judging (``check_frame``: the codec's rules,
the direction, the checksum rule, one whole frame), so what the dialog says
before Enter is what the Controller will say after it: a frame it shows as
breaking no rule is sent, one it shows breaking a rule needs force.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.protocol.frame_text import check_frame, frame_alone, frame_from_text
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.rules import Violation


@dataclass(frozen=True)
class TypedFrame:
    """What ``text`` stands for going ``direction``: its bytes, what they mean
    alone and the rules they break; or, if it is no frame, why (``error``)."""

    text: str
    direction: Direction
    data: bytes | None = None
    error: str = ""
    violations: tuple[Violation, ...] = ()
    observation: Observation | None = None


def judge_bytes(data: bytes, direction: Direction, checksum_rule: str, text: str = "") -> TypedFrame:
    """Bytes as the Controller judges a typed frame before sending it."""
    try:
        violations = tuple(check_frame(data, direction, checksum_rule))
    except ValueError as e:  # an unknown checksum rule: the Controller would fail the same way
        return TypedFrame(text, direction, data, str(e))
    observations, _ = frame_alone(data, direction, checksum_rule)
    return TypedFrame(text, direction, data, "", violations, observations[0] if observations else None)


def read_typed(text: str, direction: Direction, checksum_rule: str) -> TypedFrame:
    """The typed text read and judged; never raises."""
    try:
        data = frame_from_text(text)
    except ValueError as e:
        return TypedFrame(text, direction, error=str(e))
    return judge_bytes(data, direction, checksum_rule, text)
