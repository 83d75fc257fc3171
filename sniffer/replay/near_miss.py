"""How the stub matches a request to a recorded one, and what it says on a miss.

A cassette tool that only says "no match" leaves the user diffing by hand;
WireMock's near-miss report is what users of VCR.py and go-vcr keep asking
for.  So every request the stub serves is a ``Recorded`` entry with the fields
a match may look at (kind, channel, value, position), a ``Match`` names which
of them must agree, and on a miss ``closest`` ranks the recorded requests by
the fields that differ, most telling first, so the line says *what* to change.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.protocol.text import escape

FIELDS = ("kind", "channel", "value", "order")
DEFAULT_MATCH = "kind,channel,order"  # the stub's behaviour before --match existed
NEAR_MISSES = 3  # closest recorded requests shown on a miss


@dataclass(frozen=True, slots=True)
class Recorded:
    """One recorded request that got (or may get) an answer.

    ``value`` is the whole request frame: two Sensor Requests on one channel
    differ in value when any byte differs (value fields, checksum).
    ``position`` is its place among the connection's answerable requests."""

    conn: int
    position: int
    kind: str
    channel: int | None
    value: bytes
    text: str

    def as_dict(self) -> dict:
        return {"conn": self.conn, "position": self.position, "kind": self.kind, "channel": self.channel,
                "request": escape(self.value), "text": self.text}


@dataclass(frozen=True, slots=True)
class Match:
    """Which fields must agree for a recorded answer to serve a request.

    ``order``: the k-th matching request gets the k-th recorded answer (then
    the stub's --when-exhausted rule); without it every matching request gets
    the first recorded answer."""

    channel: bool = True
    value: bool = False
    order: bool = True

    @classmethod
    def parse(cls, text: str) -> Match:
        """``"kind,channel,value,order"`` or a part of it; ValueError naming the
        bad word.  ``kind`` is required: an answer of another kind cannot serve."""
        words = [w.strip() for w in text.split(",") if w.strip()]
        for word in words:
            if word not in FIELDS:
                raise ValueError(f"--match: unknown field {word!r}; choose from {','.join(FIELDS)}")
        if "kind" not in words:
            raise ValueError(f"--match must include kind (e.g. --match {DEFAULT_MATCH})")
        return cls(channel="channel" in words, value="value" in words, order="order" in words)

    def text(self) -> str:
        return ",".join(f for f, on in zip(FIELDS, (True, self.channel, self.value, self.order), strict=True) if on)

    def key(self, kind: str, channel: int | None, value: bytes) -> tuple:
        """The group a request (or a recorded one) falls in: equal keys match."""
        return (kind, channel if self.channel else None, value if self.value else None)


@dataclass(frozen=True, slots=True)
class NearMiss:
    """A recorded request close to the one missed, and the fields that differ."""

    recorded: Recorded
    differs: dict[str, tuple[object, object]]  # field: (asked, recorded)

    def line(self) -> str:
        shown = "; ".join(f"{f} {_show(a)} here, {_show(r)} recorded" for f, (a, r) in self.differs.items())
        return f"#{self.recorded.conn} request {self.recorded.position} {self.recorded.text}: {shown or 'same'}"

    def as_dict(self) -> dict:
        return {**self.recorded.as_dict(),
                "differs": {f: {"here": _json(a), "recorded": _json(r)} for f, (a, r) in self.differs.items()}}


def _show(value: object) -> str:
    return escape(value) if isinstance(value, bytes) else str(value)


def _json(value: object) -> object:
    return escape(value) if isinstance(value, bytes) else value


def closest(asked: Recorded, recorded: list[Recorded], limit: int = NEAR_MISSES) -> list[NearMiss]:
    """Up to ``limit`` recorded requests nearest ``asked``: a differing kind
    weighs most, then channel, then value, then distance in position.  A
    value difference is named only between requests of one kind and channel:
    across those, the frames differ as a matter of course.  A request
    recorded many times is shown once, at its nearest position."""
    def rank(r: Recorded) -> tuple:
        return (r.kind != asked.kind, r.channel != asked.channel, r.value != asked.value,
                abs(r.position - asked.position), r.conn)

    misses: list[NearMiss] = []
    shown: set[tuple] = set()
    for r in sorted(recorded, key=rank):
        if len(misses) == limit or (r.kind, r.channel, r.value) in shown:
            continue  # the same request again says nothing new: the nearest stands for it
        shown.add((r.kind, r.channel, r.value))
        differs: dict[str, tuple[object, object]] = {}
        same_place = r.kind == asked.kind and r.channel == asked.channel  # else the frames differ anyway
        for name, here, there in (("kind", asked.kind, r.kind), ("channel", asked.channel, r.channel),
                                  ("value", asked.value if same_place else b"", r.value if same_place else b""),
                                  ("position", asked.position, r.position)):
            if here != there:
                differs[name] = (here, there)
        misses.append(NearMiss(r, differs))
    return misses
