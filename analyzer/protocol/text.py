"""Bytes as text a person can read and type back, losslessly."""

from __future__ import annotations

import re
from enum import IntEnum

_SPECIAL = {0x5C: "\\\\", 0x0D: "\\r", 0x0A: "\\n", 0x09: "\\t"}
_ESCAPES = [_SPECIAL.get(b) or (chr(b) if 0x20 <= b < 0x7F else f"\\x{b:02x}") for b in range(256)]
_TOKEN = re.compile(r"\\(x[0-9a-fA-F]{2}|[\\rnt])")
_UNESCAPE = {"\\": 0x5C, "r": 0x0D, "n": 0x0A, "t": 0x09}


def escape(data: bytes) -> str:
    """Printable ASCII as itself, everything else as a backslash escape."""
    return "".join([_ESCAPES[b] for b in data])


def printable(text: str) -> str:
    """Text from a file or the wire made safe to show: every character Python
    does not call printable (control characters such as ESC, C1 controls, bidi
    and other format characters, line separators, surrogates) as an escape in
    the notation of ``escape`` (\\x1b, \\r, \\n, \\t, \\x85, \\u202e).  A terminal
    then shows it and never obeys it.  Backslashes are left as they are, so the
    result is unchanged when escaped again (escaped frames, paths)."""
    if text.isprintable():
        return text
    return "".join(c if c.isprintable() else _char_escape(c) for c in text)


def _char_escape(c: str) -> str:
    n = ord(c)
    if n < 0x80:
        return _ESCAPES[n]
    return f"\\x{n:02x}" if n < 0x100 else f"\\u{n:04x}" if n < 0x10000 else f"\\U{n:08x}"


def unescape(text: str) -> bytes:
    """The inverse of ``escape``; also accepts unescaped non-ASCII as UTF-8."""
    out = bytearray()
    pos = 0
    for m in _TOKEN.finditer(text):
        out += text[pos:m.start()].encode()
        token = m.group(1)
        out.append(int(token[1:], 16) if token[0] == "x" else _UNESCAPE[token])
        pos = m.end()
    out += text[pos:].encode()
    return bytes(out)


def shorten(text: str, width: int) -> str:
    """Escaped text cut to ``width`` characters, ending in '…' when cut, and
    never in the middle of an escape such as ``\\x0c``: a cut is never silent."""
    if len(text) <= width:
        return text
    cut = text[:width - 1]
    tail = cut.rfind("\\", max(len(cut) - 3, 0))
    if tail != -1 and (text[tail:tail + 2] == "\\x" or text[tail + 1:tail + 2] in "rnt\\"):
        end = tail + (4 if text[tail:tail + 2] == "\\x" else 2)
        if end > len(cut):
            cut = cut[:tail]
    return cut + "…"


_SIZE = re.compile(r"^\s*(\d+(?:\.\d+)?)\s*([kmgt]?)i?b?\s*$", re.IGNORECASE)
_UNITS = {"": 1, "k": 1 << 10, "m": 1 << 20, "g": 1 << 30, "t": 1 << 40}


def parse_size(text: str) -> int:
    """A byte count as people write it: 500000, 100k, 64M, 2G (powers of 1024).
    ValueError for anything else.  Here rather than with the command line's
    parameter type, so a library setting (WHIZTAP_MAX_CHUNK) reads sizes the
    same way without importing the command line."""
    m = _SIZE.match(text)
    if m is None or float(m.group(1)) <= 0:
        raise ValueError(f"{text!r} is not a size such as 1000000, 500k or 64M")
    return int(float(m.group(1)) * _UNITS[m.group(2).lower()])


def plural(n: int, word: str, words: str | None = None) -> str:
    """A count and its noun agreeing, for every line people read: '1 error',
    '2 errors', '1,024 entries' (``words``: the plural when it is not
    ``word`` + 's'; give ``word`` twice for a noun that does not change, '2 info').
    One helper, so that no output says '1 errors' or hedges with '(s)'."""
    return f"{n:,} {word if n == 1 else words or word + 's'}"


def human_bytes(n: int) -> str:
    """``n`` bytes in decimal units: '512 B', '1.5 kB', '32.0 MB'."""
    if n < 1000:
        return f"{n} B"
    size = n / 1000
    for unit in ("kB", "MB"):
        if size < 1000:
            return f"{size:.1f} {unit}"
        size /= 1000
    return f"{size:.1f} GB"


class LowerNamed(IntEnum):
    """An IntEnum shown (``str``, f-strings) as its member's name in lower case,
    "servo" or "error": an int everywhere else."""

    def __str__(self) -> str:
        return self.name.lower()
