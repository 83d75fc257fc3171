"""Recorded against replayed: is a server's answer the same as the one recorded?

Pure logic over session observations, so the replayer, the stub and the TUI
judge answers alike.  Three modes:

- ``exact``: the bytes must be identical.  Tolerances and ignored fields, when
  given, forgive a byte difference confined to those fields.
- ``structure``: same item kind, message and channel, and equal fields, except
  values that vary by nature (sensor readings, servo positions in motion,
  image sizes), which are only checked for their range, or held within a
  ``FIELD=N`` tolerance when one is given.
- ``none``: nothing is compared; every answer is ``ignored``.

Why servo positions are judged by context: a servo that had reached the
position the recording's client sent it to is at rest, and a replay at the
same pace must find it there; one still travelling (or swept by a script)
reads whatever the clock says, so only the range can be checked.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from enum import StrEnum
from typing import Any

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.codec import MAX_SENSOR_DATA, MAX_SEND_VALUE, MAX_SERVO_DATA
from whiztap.analyzer.protocol.describe import meaning, response_meaning
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.messages import (
    CameraImage,
    ChannelResponse,
    ConfigurationSettings,
    NormalSend,
    PlayInternalScript,
    SensorRequest,
    StopInternalScript,
    UnitType,
)
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.text import escape

EXPECTS_ANSWER = ("Fetch Configuration Settings", "Fetch Camera Image", "Sensor Request",
                  "Servo Position Request")


class CompareMode(StrEnum):
    EXACT = "exact"
    STRUCTURE = "structure"
    NONE = "none"


class Status(StrEnum):
    MATCH = "match"
    MISMATCH = "mismatch"
    MISSING = "missing"  # recorded an answer, the replay got none
    EXTRA = "extra"  # the replay got an answer the recording does not have
    UNANSWERED = "unanswered"  # neither got one: the same
    IGNORED = "ignored"  # not compared (mode none, or an ignored kind)


_GOOD = frozenset({Status.MATCH, Status.UNANSWERED, Status.IGNORED})

# Fields whose values vary by nature: (lowest, highest) a good value may take.
VARYING: dict[str, tuple[float, float | None]] = {
    "sensor_value": (0, MAX_SENSOR_DATA),
    "servo_position": (0, MAX_SEND_VALUE),
    "data": (0, MAX_SERVO_DATA),  # a response whose request is unknown
    "size": (1, None),  # an image's byte count
}
LATENCY_TOLERANCE_MS = 100.0  # two real runs never answer in the same microsecond
FIELDS = ("kind", "message", "channel", "sensor_value", "servo_position", "data",
          "channels", "units", "format", "size", "text")
# What --ignore-kind accepts: answer item kinds, and responses by what they answer.
IGNORABLE_KINDS = ("response", "config", "image", "handshake", "unframed", "sensor", "servo")


class CompareError(WhiztapError, ValueError):
    """A comparison rule that cannot be used (the message says why, in one line)."""


@dataclass(frozen=True, slots=True)
class CompareRules:
    mode: CompareMode = CompareMode.STRUCTURE
    tolerances: Mapping[str, float] = field(default_factory=dict)
    ignore_fields: frozenset[str] = frozenset()
    ignore_kinds: frozenset[str] = frozenset()

    @classmethod
    def parse(cls, mode: str, tolerances: Iterable[str] = (), ignore_fields: Iterable[str] = (),
              ignore_kinds: Iterable[str] = ()) -> CompareRules:
        """Rules from command-line text (``sensor_value=20``); raises CompareError."""
        try:
            compare_mode = CompareMode(mode)
        except ValueError:
            raise CompareError(f"unknown compare mode {mode!r}: expected exact, structure or none") from None
        limits: dict[str, float] = {}
        for text in tolerances:
            name, sep, value = text.partition("=")
            _check_field(name.strip(), "--tolerance")
            try:
                limit = float(value)
            except ValueError:
                limit = -1.0
            if not sep or limit < 0:
                raise CompareError(f"--tolerance wants FIELD=N with N >= 0, got {text!r}")
            limits[name.strip()] = limit
        for name in ignore_fields:
            _check_field(name, "--ignore-field")
        for kind in ignore_kinds:
            if kind not in IGNORABLE_KINDS:
                raise CompareError(f"--ignore-kind: unknown kind {kind!r}; kinds are {', '.join(IGNORABLE_KINDS)}")
        return cls(compare_mode, limits, frozenset(ignore_fields), frozenset(ignore_kinds))

    def ignores(self, answer: Observation) -> bool:
        kinds = self.ignore_kinds
        if not kinds:
            return False
        return answer.item.kind.value in kinds or response_meaning(answer) in kinds

    def describe(self) -> str:
        parts = [f"compare {self.mode}"]
        parts += [f"{name}±{limit:g}" for name, limit in sorted(self.tolerances.items())]
        parts += [f"ignoring {name}" for name in sorted(self.ignore_fields | self.ignore_kinds)]
        return ", ".join(parts)


def _check_field(name: str, option: str) -> None:
    if name not in FIELDS:
        raise CompareError(f"{option}: unknown field {name!r}; fields are {', '.join(FIELDS)}")


@dataclass(frozen=True, slots=True)
class FieldDiff:
    field: str
    recorded: Any
    replayed: Any
    note: str = ""


@dataclass(frozen=True, slots=True)
class Verdict:
    status: Status
    differences: tuple[FieldDiff, ...] = ()

    @property
    def match(self) -> bool:
        return self.status in _GOOD


# -- what is compared ------------------------------------------------------------------


def _units(channels: tuple) -> str:
    """A channel map as runs: '0-5 servo, 6-8 switch0, ...'."""
    names = []
    for c in channels:
        unit = str(UnitType(c.unit_type)) if c.unit_type in (0, 1, 2) else f"unit{c.unit_type}"
        names.append(unit + (str(c.switch_type) if c.unit_type == UnitType.SWITCH else ""))
    runs: list[tuple[int, int, str]] = []
    for ch, name in enumerate(names):
        if runs and runs[-1][2] == name:
            runs[-1] = (runs[-1][0], ch, name)
        else:
            runs.append((ch, ch, name))
    return ", ".join(f"{a} {n}" if a == b else f"{a}-{b} {n}" for a, b, n in runs)


def answer_fields(answer: Observation) -> dict[str, Any]:
    """The fields of a server item that a comparison looks at, by name."""
    item, message = answer.item, answer.message
    out: dict[str, Any] = {"kind": item.kind.value}
    if message is None:
        out["text"] = escape(item.raw)
        return out
    out["message"] = message.title
    if isinstance(message, ChannelResponse):
        out["channel"] = message.channel
        as_ = response_meaning(answer)
        if as_ == "servo":
            out["servo_position"] = message.data / 4
        elif as_ == "sensor":
            out["sensor_value"] = message.data
        else:
            out["data"] = message.data
    elif isinstance(message, ConfigurationSettings):
        out["channels"] = len(message.channels)
        out["units"] = _units(message.channels)
    elif isinstance(message, CameraImage):
        out["format"] = message.format
        out["size"] = len(message.data)
    return out


def _numbers(a: object, b: object) -> tuple[float, float] | None:
    """Both values, when both are numbers (so a tolerance or a range applies)."""
    return (a, b) if isinstance(a, (int, float)) and isinstance(b, (int, float)) else None


def _field_diffs(recorded: Observation, replayed: Observation, rules: CompareRules,
                 strict: bool, at_rest: bool) -> list[FieldDiff]:
    mine, theirs = answer_fields(recorded), answer_fields(replayed)
    diffs = []
    for name in [n for n in FIELDS if n in mine or n in theirs]:
        if name in rules.ignore_fields:
            continue
        a, b = mine.get(name), theirs.get(name)
        limit = rules.tolerances.get(name)
        numbers = _numbers(a, b)
        if limit is not None and numbers is not None:
            a, b = numbers
            if abs(a - b) > limit:
                diffs.append(FieldDiff(name, a, b, f"differs by {abs(a - b):g}, tolerance {limit:g}"))
        elif name in VARYING and not strict and not (name == "servo_position" and at_rest) and numbers is not None:
            a, b = numbers
            low, high = VARYING[name]
            if b < low or (high is not None and b > high):
                diffs.append(FieldDiff(name, a, b, f"out of range {low}-{high if high is not None else ''}"))
        elif a != b:
            note = "servo at rest in the recording" if name == "servo_position" and at_rest else ""
            diffs.append(FieldDiff(name, a, b, note))
    return diffs


def compare(recorded: Observation | None, replayed: Observation | None, rules: CompareRules,
            at_rest: bool = False) -> Verdict:
    """Judge one answer.  ``at_rest``: the recorded answer is a servo position
    reached and held (see ``ServoMotion``), so it must be equal, not just in range."""
    answer = recorded if recorded is not None else replayed
    if answer is None:
        return Verdict(Status.UNANSWERED)
    if rules.mode is CompareMode.NONE or rules.ignores(answer):
        return Verdict(Status.IGNORED)
    if recorded is None:
        return Verdict(Status.EXTRA)
    if replayed is None:
        return Verdict(Status.MISSING)
    if rules.mode is CompareMode.EXACT:
        if recorded.item.raw == replayed.item.raw:
            return Verdict(Status.MATCH)
        diffs = _field_diffs(recorded, replayed, rules, strict=True, at_rest=at_rest)
        if not diffs and not (rules.tolerances or rules.ignore_fields):
            diffs = [FieldDiff("bytes", escape(recorded.item.raw), escape(replayed.item.raw),
                               "same meaning, different bytes")]
        return Verdict(Status.MISMATCH if diffs else Status.MATCH, tuple(diffs))
    diffs = _field_diffs(recorded, replayed, rules, strict=False, at_rest=at_rest)
    return Verdict(Status.MISMATCH if diffs else Status.MATCH, tuple(diffs))


# -- context: requests and servo motion ------------------------------------------------------


def answer_key(request: Observation) -> tuple[tuple[str, int | None], bool] | None:
    """What answers a request, as ((request title, channel), certain).

    None for a command that expects no answer.  A frame that only may be a
    Sensor Request (no channel map known) gives the Sensor Request key with
    ``certain`` False: answer it if an answer was recorded, never complain.
    """
    if request.direction is not Direction.C2S or request.item.kind is not ItemKind.COMMAND:
        return None
    message = request.message
    if message is not None:
        if message.title not in EXPECTS_ANSWER:
            return None
        return (message.title, getattr(message, "channel", None)), True
    for candidate in request.candidates:
        if isinstance(candidate, SensorRequest):
            return (candidate.title, candidate.channel), False
    return None


class ServoMotion:
    """Follows a recorded session to tell whether a servo reading shows it at rest:
    equal to the position last sent to that servo, with no internal script playing."""

    def __init__(self) -> None:
        self._targets: dict[int, float] = {}
        self._script = False

    def observe(self, obs: Observation) -> None:
        message = obs.message
        if isinstance(message, NormalSend):
            self._targets[message.channel] = float(message.value)
        elif isinstance(message, PlayInternalScript):
            self._script = True
        elif isinstance(message, StopInternalScript):
            self._script = False

    def at_rest(self, answer: Observation) -> bool:
        message = answer.message
        if not isinstance(message, ChannelResponse) or response_meaning(answer) != "servo" or self._script:
            return False
        return self._targets.get(message.channel) == message.data / 4


# -- for people ------------------------------------------------------------------------------


def _cell(text: str, width: int) -> str:
    return text if len(text) <= width else text[:width - 3] + "..."


def _value(value: Any) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:g}"
    return str(value)


def side_by_side(recorded: Observation | None, replayed: Observation | None, verdict: Verdict,
                 width: int = 40) -> list[str]:
    """Recorded and replayed answers in two columns: bytes, meaning, then each
    field that differs with why."""
    def column(obs: Observation | None, absent: str) -> tuple[str, str]:
        if obs is None:
            return absent, ""
        text, said = escape(obs.item.raw), meaning(obs)
        return text, "" if said == text else said  # handshake words mean themselves

    left = column(recorded, "(no answer recorded)")
    right = column(replayed, "(no answer)")
    rows = [("recorded", "replayed"), (left[0], right[0]), (left[1], right[1])]
    rows += [(f"{d.field}: {_value(d.recorded)}", f"{d.field}: {_value(d.replayed)}"
              + (f"  ({d.note})" if d.note else "")) for d in verdict.differences]
    return [f"  {_cell(a, width):<{width}} | {_cell(b, 2 * width)}".rstrip() for a, b in rows if a or b]


def headline(verdict: Verdict, conn: int, t_s: float, request: Observation | None, what: str = "") -> str:
    """'MISMATCH c1 at 0.001507 s after rr1-12--0--0-ss1 (Sensor Request ch 12)'."""
    after = what
    if request is not None:
        after = f"{escape(request.item.raw)} ({meaning(request)})"
    return f"{verdict.status.upper()} c{conn} at {t_s:.6f} s" + (f" after {after}" if after else "")
