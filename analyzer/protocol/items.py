"""What a framer cuts a stream into: the item kinds, why bytes stay unframed, the item.

Apart from the framer (``framing.py``) so that its scanners in other modules
(``images.py``) share the vocabulary without importing the framer.
"""

from __future__ import annotations

from enum import StrEnum
from typing import NamedTuple

NEED_MORE = -1  # returned by item scanners: the item may still complete


class ItemKind(StrEnum):
    COMMAND = "command"  # rr1-D1--D2--D3-ss1
    RESPONSE = "response"  # cr1-D1--D2--D3-ss1
    CONFIG = "config"  # sr1-[count] digits -ss1
    SET_CONFIG = "set_config"  # sr1-25-- triples [chk] --0-ss1
    HANDSHAKE = "handshake"  # sendchkpass / readytogo / Failed Validation
    PASSWORD = "password"  # the client's answer to sendchkpass
    IMAGE = "image"  # a JPEG or PNG byte stream
    EOL = "eol"  # a run of CR/LF bytes between items
    UNFRAMED = "unframed"  # anything else, with a reason


    @property
    def words(self) -> str:
        """The kind as a person who read the spec knows it, with its article
        ('a Sensor/Servo Response'): what rule details and messages say, never
        the value, which is an identifier."""
        return _KIND_WORDS[self]


_KIND_WORDS = {
    ItemKind.COMMAND: "a command",
    ItemKind.RESPONSE: "a Sensor/Servo Response",
    ItemKind.CONFIG: "a Configuration Settings message",
    ItemKind.SET_CONFIG: "a Set Configuration Settings message",
    ItemKind.HANDSHAKE: "a handshake message",
    ItemKind.PASSWORD: "a password",
    ItemKind.IMAGE: "a Camera Image",
    ItemKind.EOL: "a line break",
    ItemKind.UNFRAMED: "unframed bytes",
}


class Unframed(StrEnum):
    """Why bytes were emitted as an ``unframed`` item."""

    GARBAGE = "garbage"  # bytes that start no known item
    TRUNCATED = "truncated"  # a header whose item never completed
    OVERSIZE = "oversize"  # an item grew past the framer's size limit


class Item(NamedTuple):
    """One framed piece of a stream.

    A NamedTuple rather than a dataclass: the framer makes one per frame on the
    hot path, and tuples are several times cheaper to build while still immutable.
    """

    kind: ItemKind
    raw: bytes
    t_start_ns: int  # arrival time of the chunk holding the first byte
    t_end_ns: int  # arrival time of the chunk holding the last byte
    reason: Unframed | None = None


Scanned = tuple[int, ItemKind, Unframed | None]
"""What an item scanner found at a position: the item's length, its kind, and
why it is unframed (None: it is not)."""
Scan = Scanned | int | None
"""An item scanner's answer: what it found; NEED_MORE, the item may still
complete; or None, the bytes there are not its kind of item."""

