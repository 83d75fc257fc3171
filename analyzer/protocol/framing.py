"""Cut one direction of a Progwhiz byte stream into items, losing nothing.

The framer is sans-IO: callers feed it chunks with the time they arrived and get
back the items those chunks completed.  Every byte of the stream ends up in
exactly one item, and the items do not depend on how the stream was chunked,
which is what lets a recording be re-framed later with identical results.
"""

from __future__ import annotations

import re
from enum import StrEnum
from typing import NamedTuple

DEFAULT_MAX_ITEM = 64 * 1024
MIN_MAX_ITEM = 1024  # above the longest Configuration Settings frame (255 channels)
DEFAULT_MAX_IMAGE = 32 * 1024 * 1024  # camera pictures: the spec sets no limit


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


HANDSHAKE_WORDS = (b"sendchkpass", b"readytogo", b"Failed Validation")
TRAILER = b"-ss1"
SET_CONFIG_PREFIX = b"sr1-25--"
SET_CONFIG_TRAILER = b"--0-ss1"
LAYOUT_DATA1 = 25  # Set Configuration's Data1 as one raw byte (the Layout line's reading)
JPEG_SOI = b"\xff\xd8\xff"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
TEXT_FRAME_MAX = 48  # longest rr1/cr1 frame considered before giving up on a trailer
SMALL_READ = 512  # reads up to this size first try to be whole text frames

# Fast path: well-formed text frames.  Anything else goes through the slow path,
# which still frames it (with spaces, letters, wide fields) as long as a trailer
# comes before the next header.
_TEXT_RUN = re.compile(rb"(?:[rc]r1-[0-9]{1,5}--[0-9]{1,5}--[0-9]{1,5}-ss1)+")
_new_item = tuple.__new__  # Item without its Python-level __new__: the hot path's biggest cost
_SYNC = re.compile(
    rb"rr1-|cr1-|sr1-|sendchkpass|readytogo|Failed Validation|\xff\xd8\xff|\x89PNG\r\n\x1a\n|[\r\n]"
)
_HEADER = re.compile(rb"rr1-|cr1-|sr1-")
_SYNC_TOKENS = (
    b"rr1-", b"cr1-", b"sr1-", *HANDSHAKE_WORDS, JPEG_SOI, PNG_SIGNATURE,
)
_SYNC_LONGEST = max(len(t) for t in _SYNC_TOKENS)
_NEED_MORE = -1  # returned by item scanners: the item may still complete


class Framer:
    """Frames one direction of a connection.

    ``feed()`` returns completed items; ``end()`` flushes what is left when the
    stream closes.  A client-side framer can be told that the server asked for a
    password (``expect_password()``); it then takes the leading text as the
    password until a line break, a frame header, or ``close_password()``.
    """

    def __init__(self, max_item: int = DEFAULT_MAX_ITEM, max_image: int = DEFAULT_MAX_IMAGE) -> None:
        """``max_item`` bounds every item but camera images, which ``max_image``
        bounds (at least ``max_item``): a picture of several megabytes is one item,
        while a frame that never ends still costs at most ``max_item`` of memory."""
        if max_item < MIN_MAX_ITEM:
            raise ValueError(f"max_item must be at least {MIN_MAX_ITEM} bytes")
        self.max_item = max_item
        self.max_image = max(max_image, max_item)
        # Where the scan of an image at the start of the buffer resumes, so a large
        # picture arriving in many reads is walked once, not once per read.
        self._resume: tuple[int, int] | None = None
        self._buf: bytearray | bytes = bytearray()  # bytes only while a feed scans a fresh chunk
        # (offset in _buf, arrival time) for each chunk still partly in _buf
        self._marks: list[tuple[int, int]] = []
        self._password_mode = False
        self._ended = False
        self._window = 0  # end of the bytes the current scan may look at
        self._final = False  # the current scan is end()'s: nothing more will come

    @property
    def buffered(self) -> int:
        """Bytes held for an item not yet complete."""
        return len(self._buf)

    def expect_password(self) -> None:
        self._password_mode = True

    def close_password(self, t_ns: int) -> list[Item]:
        """The server has judged the password: whatever is pending is the password."""
        if not self._password_mode:
            return []
        items = self._scan(t_ns, first_new=len(self._buf), final=False)
        if self._password_mode and self._buf:
            items.append(Item(ItemKind.PASSWORD, bytes(self._buf), self._start_time(0, t_ns), t_ns))
            self._drop(len(self._buf))
        self._password_mode = False
        return items

    def feed(self, data: bytes, t_ns: int) -> list[Item]:
        if self._ended:
            # Bytes after the stream's end: only a file written out of order
            # (another writer, an older whiztap) says so.  Frame them as they
            # come rather than refuse the rest of the recording.
            self._ended = False
        if not data:
            return []
        first_new = len(self._buf)
        if (not first_new and len(data) <= SMALL_READ and not self._password_mode
                and _TEXT_RUN.fullmatch(data) is not None):
            # the commonest read of request/response traffic: a whole frame or
            # two, nothing pending (larger reads rarely end on a frame's end)
            pieces = data.split(TRAILER)
            pieces.pop()
            return [_new_item(Item, (ItemKind.COMMAND if p[0] == 0x72 else ItemKind.RESPONSE, p + TRAILER,
                                     t_ns, t_ns, None)) for p in pieces]
        self._marks.append((first_new, t_ns))
        if first_new:
            self._buf += data
            if self._resume is not None and self._image_pending():
                return []
        else:
            self._buf = data  # nothing pending: scan the chunk itself, copy only what is left
        items = self._scan(t_ns, first_new, final=False)
        if type(self._buf) is bytes:
            self._buf = bytearray(self._buf)
        return items

    def end(self, t_ns: int) -> list[Item]:
        """The stream closed: flush everything, incomplete items as ``unframed``."""
        self._ended = True
        return self._scan(t_ns, first_new=len(self._buf), final=True)

    # -- internals -------------------------------------------------------------

    def _start_time(self, pos: int, t_ns: int) -> int:
        start = t_ns
        for offset, t in self._marks:
            if offset > pos:
                break
            start = t
        return start

    def _scan(self, t_ns: int, first_new: int, final: bool) -> list[Item]:
        items: list[Item] = []
        data = bytes(self._buf)  # one copy per scan; slicing bytes then copies once
        pos = 0
        n = len(data)
        run_match = _TEXT_RUN.match
        command, response = ItemKind.COMMAND, ItemKind.RESPONSE
        while pos < n:
            if not self._password_mode:
                # Fast path: a run of well-formed text frames.  Inside one, "-ss1"
                # occurs only as a trailer, so a split finds every frame at C speed.
                m = run_match(data, pos)
                if m is not None:
                    end = m.end()
                    pieces = data[pos:end].split(TRAILER)
                    pieces.pop()
                    if pos < first_new:
                        first = pieces.pop(0)
                        items.append(_new_item(Item, (command if first[0] == 0x72 else response, first + TRAILER,
                                                      self._start_time(pos, t_ns), t_ns, None)))
                    items += [_new_item(Item, (command if p[0] == 0x72 else response, p + TRAILER, t_ns, t_ns, None))
                              for p in pieces]
                    pos = end
                    continue
            step = self._scan_slow(pos, final)
            if step is None:
                break
            length, kind, reason = step
            if length > self.max_item:
                limit = self.max_image if self._is_image(pos) else self.max_item
                if length > limit:
                    # cut exactly where a partial stream would have been cut
                    length, kind, reason = limit, ItemKind.UNFRAMED, Unframed.OVERSIZE
            t_start = t_ns if pos >= first_new else self._start_time(pos, t_ns)
            items.append(Item(kind, data[pos:pos + length], t_start, t_ns, reason))
            pos += length
        if pos:
            self._drop(pos)
        return items

    def _drop(self, n: int) -> None:
        """Forget the first n bytes, keeping the arrival time of the byte now first."""
        self._resume = None
        if type(self._buf) is bytes:
            self._buf = bytearray(memoryview(self._buf)[n:])
        else:
            del self._buf[:n]
        kept: list[tuple[int, int]] = []
        for offset, t in self._marks:
            if offset <= n:
                kept = [(0, t)]
            else:
                kept.append((offset - n, t))
        self._marks = kept if self._buf else []

    def _scan_slow(self, pos: int, final: bool) -> tuple[int, ItemKind, Unframed | None] | None:
        """Identify the item at pos: (length, kind, reason), or None to wait for data.

        Scanners look only at the window of ``max_item`` bytes from pos.  That keeps
        every decision independent of how much data happens to be buffered: an item
        that cannot be decided within the window is cut as ``oversize`` whether the
        rest of it has arrived yet or not.
        """
        self._window = min(len(self._buf), pos + self.max_item)
        self._final = final
        if self._password_mode:
            result = self._scan_password(pos, final)
        else:
            for scanner in _SCANNERS:
                result = scanner(self, pos)
                if result is not None:
                    break
            else:
                result = self._scan_garbage(pos, Unframed.GARBAGE)
        if result == _NEED_MORE:
            return self._wait_or_cut(pos, final)
        return result

    def _image_pending(self) -> bool:
        """Whether the image at the start of the buffer still needs more bytes
        (looking only at what arrived since the last look)."""
        self._window = min(len(self._buf), self.max_item)
        self._final = False
        scanner = Framer._scan_jpeg if self._buf[0] == 0xFF else Framer._scan_png
        return len(self._buf) < self.max_image and scanner(self, 0) == _NEED_MORE

    def _is_image(self, pos: int) -> bool:
        buf = self._buf
        return buf.startswith(JPEG_SOI, pos) or buf.startswith(PNG_SIGNATURE, pos)

    def _wait_or_cut(self, pos: int, final: bool) -> tuple[int, ItemKind, Unframed | None] | None:
        """An item has begun but is incomplete: wait, unless the stream ended or it is too big."""
        pending = len(self._buf) - pos
        limit = self.max_image if self._is_image(pos) else self.max_item
        if pending >= limit:
            return limit, ItemKind.UNFRAMED, Unframed.OVERSIZE
        if final:
            return pending, ItemKind.UNFRAMED, Unframed.TRUNCATED
        return None

    def _scan_garbage(self, pos: int, reason: Unframed):
        """Bytes from pos up to the next sync point become one ``unframed`` item.

        pos itself is never a usable sync point here (nothing matched there, or the
        item starting there failed), so the search starts one byte later.  With no
        sync point in a full window, the cut falls where no token could straddle it.
        """
        window = self._window
        m = _SYNC.search(self._buf, pos + 1, window)
        if m is not None:
            if self._in_partial_png(pos, m.start()):
                return None  # the line break may be inside a PNG signature still arriving
            return m.start() - pos, ItemKind.UNFRAMED, reason
        if window - pos >= self.max_item:
            return self.max_item - _SYNC_LONGEST + 1, ItemKind.UNFRAMED, Unframed.OVERSIZE
        if self._final:
            return window - pos, ItemKind.UNFRAMED, reason
        return None

    def _in_partial_png(self, pos: int, at: int) -> bool:
        """Whether the sync point at ``at`` lies inside the start of a PNG signature
        that the data so far ends in (the signature holds CR and LF itself)."""
        buf, window = self._buf, self._window
        if self._final or window - pos >= self.max_item or buf[at] not in (0x0D, 0x0A):
            return False
        start = buf.rfind(b"\x89", max(pos + 1, at - len(PNG_SIGNATURE) + 1), at)
        return start != -1 and PNG_SIGNATURE.startswith(bytes(buf[start:window]))

    def _scan_password(self, pos: int, final: bool):
        buf, window = self._buf, self._window
        cut = window
        for token in (b"\r", b"\n"):
            i = buf.find(token, pos, window)
            if i != -1:
                cut = min(cut, i)
        h = _HEADER.search(buf, pos, window)
        if h is not None:
            cut = min(cut, h.start())
        if cut == pos:
            # nothing before the break or header: the password (if any) is over
            self._password_mode = False
            return self._scan_slow(pos, final)
        if cut < window or final:
            self._password_mode = False
            return cut - pos, ItemKind.PASSWORD, None
        return _NEED_MORE

    # Each scanner returns None (not its kind of item), _NEED_MORE, or
    # (length, kind, reason).  They read only self._buf[pos:self._window].

    def _scan_text(self, pos: int):
        buf, window = self._buf, self._window
        head = bytes(buf[pos:pos + 4])
        if head not in (b"rr1-", b"cr1-"):
            return _NEED_MORE if len(head) < 4 and (b"rr1-".startswith(head) or b"cr1-".startswith(head)) else None
        kind = ItemKind.COMMAND if head[0] == 0x72 else ItemKind.RESPONSE
        body_end = pos + 4 + TEXT_FRAME_MAX  # the trailer must start before this
        t = buf.find(TRAILER, pos + 4, min(window, body_end + 3))
        h = _HEADER.search(buf, pos + 4, min(window, body_end + 3))
        if t != -1 and (h is None or h.start() > t):
            return t + 4 - pos, kind, None
        if h is not None:
            return h.start() - pos, ItemKind.UNFRAMED, Unframed.TRUNCATED
        if window < body_end + 3:
            return _NEED_MORE
        return self._scan_garbage(pos, Unframed.TRUNCATED)

    def _scan_sr1(self, pos: int):
        buf, window = self._buf, self._window
        head = bytes(buf[pos:min(window, pos + 8)])
        if not head.startswith(b"sr1-"):
            return _NEED_MORE if len(head) < 4 and b"sr1-".startswith(head) else None
        if len(head) < 8 and SET_CONFIG_PREFIX.startswith(head):
            return _NEED_MORE  # Set Configuration, or a count byte that happens to be '2'
        if head == SET_CONFIG_PREFIX:
            return self._scan_set_config(pos, pos + 8, 1, SET_CONFIG_TRAILER)
        count = buf[pos + 4]
        total = 4 + 1 + 3 * count + 4
        body = bytes(buf[pos + 5:min(window, pos + total - 4)])
        # Configuration Settings: the count byte fixes the length.  Its digits are
        # checked by the decoder, except with a count of 25, where they must be
        # digits to tell it apart from Set Configuration in its Layout-line form.
        if count != LAYOUT_DATA1 or body.isdigit() or not body:
            if window - pos < total:
                return _NEED_MORE
            if buf[pos + total - 4:pos + total] == TRAILER:
                return total, ItemKind.CONFIG, None
        if count == LAYOUT_DATA1:
            return self._scan_set_config(pos, pos + 5, 2, TRAILER)
        return self._scan_garbage(pos, Unframed.TRUNCATED)

    def _scan_set_config(self, pos: int, body: int, pad: int, trailer: bytes):
        """Find the trailer at a triple boundary: raw payload bytes never fool it.

        Valid Port# and unit type bytes are below 24, so neither a trailer nor a
        frame header can appear inside valid triples at any alignment.
        """
        buf, window = self._buf, self._window
        header = _HEADER.search(buf, body, window)
        stop = header.start() if header is not None else window
        q = body + pad  # where the trailer starts with zero triples
        size = len(trailer)
        while q + size <= window and q < stop:
            if buf[q:q + size] == trailer:
                return q + size - pos, ItemKind.SET_CONFIG, None
            q += 3
        if header is not None:
            return header.start() - pos, ItemKind.UNFRAMED, Unframed.TRUNCATED
        return _NEED_MORE

    def _scan_handshake(self, pos: int):
        buf, window = self._buf, self._window
        for word in HANDSHAKE_WORDS:
            if buf.startswith(word, pos, window):
                return len(word), ItemKind.HANDSHAKE, None
        tail = bytes(buf[pos:window])
        if any(len(tail) < len(w) and w.startswith(tail) for w in HANDSHAKE_WORDS):
            return _NEED_MORE
        return None

    def _scan_eol(self, pos: int):
        """A line break: CR LF, LF, or CR alone.  A CR at the end of the data waits
        for the next byte, which may be its LF (``end()`` settles it)."""
        buf = self._buf
        first = buf[pos]
        if first == 0x0A:
            return 1, ItemKind.EOL, None
        if first != 0x0D:
            return None
        if pos + 1 == self._window:
            return (1, ItemKind.EOL, None) if self._final else _NEED_MORE
        return (2 if buf[pos + 1] == 0x0A else 1), ItemKind.EOL, None

    def _image_start(self, pos: int, signature: bytes):
        """None (no image opening with ``signature`` at pos), _NEED_MORE, or the end of its max_image window."""
        n = min(len(self._buf), pos + self.max_image)
        head = bytes(self._buf[pos:min(n, pos + len(signature))])
        if not head or not signature.startswith(head):
            return None
        return _NEED_MORE if len(head) < len(signature) else n

    def _scan_jpeg(self, pos: int):
        n = self._image_start(pos, JPEG_SOI)
        if n is None or n == _NEED_MORE:
            return n
        phase, i = self._resume if pos == 0 and self._resume is not None else (0, pos + 2)
        result = self._walk_jpeg(pos, n, phase, i) if phase == 0 else self._walk_entropy(pos, n, i)
        if result != _NEED_MORE:
            self._resume = None
        return result

    def _walk_jpeg(self, pos: int, n: int, phase: int, i: int):
        buf = self._buf
        # Marker segments up to Start Of Scan carry their own lengths.
        while True:
            if i + 2 > n:
                self._resume = (0, i) if pos == 0 else None
                return _NEED_MORE
            if buf[i] != 0xFF:
                return self._scan_garbage(pos, Unframed.GARBAGE)
            marker = buf[i + 1]
            if marker == 0xFF:
                i += 1
            elif marker == 0xD9:
                return i + 2 - pos, ItemKind.IMAGE, None
            elif 0xD0 <= marker <= 0xD7 or marker == 0x01:
                i += 2
            else:
                if i + 4 > n:
                    self._resume = (0, i) if pos == 0 else None
                    return _NEED_MORE
                seg_len = (buf[i + 2] << 8) | buf[i + 3]
                if seg_len < 2:
                    return self._scan_garbage(pos, Unframed.GARBAGE)
                i += 2 + seg_len
                if marker == 0xDA:
                    return self._walk_entropy(pos, n, i)

    def _walk_entropy(self, pos: int, n: int, i: int):
        """Entropy-coded data: FF is stuffed as FF 00; FF D0-D7 are restarts; any
        other marker (a further scan's tables) carries a length again."""
        buf = self._buf
        while True:
            j = buf.find(b"\xff", i, n)
            if j == -1 or j + 1 >= n:
                self._resume = (1, n if j == -1 else j) if pos == 0 else None
                return _NEED_MORE
            nxt = buf[j + 1]
            if nxt == 0xD9:
                return j + 2 - pos, ItemKind.IMAGE, None
            if nxt == 0xFF:
                i = j + 1
            elif nxt == 0x00 or 0xD0 <= nxt <= 0xD7:
                i = j + 2
            else:
                if j + 4 > n:
                    self._resume = (1, j) if pos == 0 else None
                    return _NEED_MORE
                i = j + 2 + ((buf[j + 2] << 8) | buf[j + 3])

    def _scan_png(self, pos: int):
        n = self._image_start(pos, PNG_SIGNATURE)
        if n is None or n == _NEED_MORE:
            return n
        buf = self._buf
        i = self._resume[1] if pos == 0 and self._resume is not None else pos + 8
        while True:
            if i + 8 > n:
                self._resume = (2, i) if pos == 0 else None
                return _NEED_MORE
            length = int.from_bytes(buf[i:i + 4], "big")
            ctype = bytes(buf[i + 4:i + 8])
            if not ctype.isalpha():
                self._resume = None
                return self._scan_garbage(pos, Unframed.GARBAGE)
            if ctype == b"IEND":
                end = i + 12 + length
                if end > n:
                    self._resume = (2, i) if pos == 0 else None
                    return _NEED_MORE
                self._resume = None
                return end - pos, ItemKind.IMAGE, None
            i += 12 + length


_SCANNERS = (
    Framer._scan_text, Framer._scan_sr1, Framer._scan_handshake,
    Framer._scan_eol, Framer._scan_jpeg, Framer._scan_png,
)
