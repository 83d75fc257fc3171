"""Cut one direction of a Progwhiz byte stream into items, losing nothing.

The framer is sans-IO: callers feed it chunks with the time they arrived and get
back the items those chunks completed.  Every byte of the stream ends up in
exactly one item, and the items do not depend on how the stream was chunked,
which is what lets a recording be re-framed later with identical results.
"""

from __future__ import annotations

import re
from collections.abc import Callable

from whiztap.analyzer.protocol.handshake import HANDSHAKE_WORDS
from whiztap.analyzer.protocol.images import JPEG_SOI, PNG_SIGNATURE, ImageScanning
from whiztap.analyzer.protocol.items import NEED_MORE as _NEED_MORE
from whiztap.analyzer.protocol.items import Item, ItemKind, Scan, Scanned, Unframed

__all__ = [  # the item vocabulary is items.py's; imported from here as ever
    "COMMAND_HEADER", "CONFIG_HEADER", "DEFAULT_MAX_IMAGE", "DEFAULT_MAX_ITEM", "FRAME_HEADERS", "JPEG_SOI",
    "MAX_PASSWORD", "MIN_MAX_ITEM", "PNG_SIGNATURE", "RESPONSE_HEADER", "SET_CONFIG_PREFIX", "Framer", "Item",
    "ItemKind", "Unframed", "unasked",
]

DEFAULT_MAX_ITEM = 64 * 1024
MIN_MAX_ITEM = 1024  # above the longest Configuration Settings frame (255 channels)
DEFAULT_MAX_IMAGE = 32 * 1024 * 1024  # camera pictures: the spec sets no limit
MAX_PASSWORD = 256  # a longer first line is no password (docs/protocol.md, A14)

COMMAND_HEADER = b"rr1-"  # a client's command
RESPONSE_HEADER = b"cr1-"  # a server's answer on a channel
CONFIG_HEADER = b"sr1-"  # Configuration Settings from the server; Set Configuration from the client
FRAME_HEADERS = (COMMAND_HEADER, RESPONSE_HEADER, CONFIG_HEADER)
TRAILER = b"-ss1"
SET_CONFIG_PREFIX = b"sr1-25--"
SET_CONFIG_TRAILER = b"--0-ss1"
LAYOUT_DATA1 = 25  # Set Configuration's Data1 as one raw byte (the Layout line's reading)
TEXT_FRAME_MAX = 48  # longest rr1/cr1 frame considered before giving up on a trailer
SMALL_READ = 512  # reads up to this size first try to be whole text frames

# Fast path: well-formed text frames.  Anything else goes through the slow path,
# which still frames it (with spaces, letters, wide fields) as long as a trailer
# comes before the next header.
_TEXT_RUN = re.compile(rb"(?:[rc]r1-[0-9]{1,5}--[0-9]{1,5}--[0-9]{1,5}-ss1)+")
_new_item = tuple.__new__  # Item without its Python-level __new__: the hot path's biggest cost
_SYNC_TOKENS = (*FRAME_HEADERS, *HANDSHAKE_WORDS, JPEG_SOI, PNG_SIGNATURE)  # where an item may begin
_HEADERS = b"|".join(FRAME_HEADERS)  # (no header holds a character special to a pattern)
_SYNC = re.compile(b"|".join(re.escape(token) for token in _SYNC_TOKENS) + rb"|[\r\n]")
_HEADER = re.compile(_HEADERS)
_PASSWORD_END = re.compile(rb"[\r\n]|" + _HEADERS)
_SYNC_LONGEST = max(len(t) for t in _SYNC_TOKENS)
_FRAMES = frozenset({ItemKind.COMMAND, ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.SET_CONFIG})


class Framer(ImageScanning):
    """Frames one direction of a connection.

    ``feed()`` returns completed items; ``end()`` flushes what is left when the
    stream closes.  A client-side framer can be told that its next line may be
    a password (``expect_password()``): that line, line breaks before it aside,
    is then one ``password`` item up to its line break or the header of a frame
    that completes, unless it begins with a frame header or runs past
    ``MAX_PASSWORD`` bytes (docs/protocol.md, A14).  ``close_password()``
    hands over what has come of it when the server judges it early.
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
        self._password_mode = False  # a password may be coming and the server has not judged it
        self._in_password = False  # the next line is scanned as a password (also after the verdict)
        self._password_begun = False  # some of it has been handed over (close_password)
        self._password_left = MAX_PASSWORD  # bytes it may still have
        self._ended = False
        self._window = 0  # end of the bytes the current scan may look at
        self._final = False  # the current scan is end()'s: nothing more will come

    @property
    def buffered(self) -> int:
        """Bytes held for an item not yet complete."""
        return len(self._buf)

    @property
    def password_pending(self) -> bool:
        """The server asked for a password and the framer is reading it: the
        proxy in the middle passes these bytes on as they come."""
        return self._password_mode

    @property
    def in_password(self) -> bool:
        """The next line, or the rest of one the server judged early, is still
        taken as a password (``password_pending`` ends at the verdict; this
        ends with the line)."""
        return self._in_password

    def expect_password(self) -> None:
        """The next line (line breaks before it aside) may be a password."""
        self._password_mode = self._in_password = True
        self._password_begun = False
        self._password_left = MAX_PASSWORD

    def close_password(self, t_ns: int) -> list[Item]:
        """The server has judged the password: what has come of it, up to a line
        break or a frame header, is a password item now; the rest of its line,
        if more comes, is one more (a server may judge at the first wrong byte)."""
        if not self._password_mode:
            return []
        self._password_mode = False
        items = self._scan(t_ns, first_new=len(self._buf), final=False)
        buf = self._buf
        if self._in_password and buf and buf[0] not in b"\r\n" and not self._may_be_header(buf):
            end = _PASSWORD_END.search(buf)
            cut = end.start() if end is not None else len(buf)
            if 0 < cut <= self._password_left:
                items.append(Item(ItemKind.PASSWORD, bytes(buf[:cut]), self._start_time(0, t_ns), t_ns))
                self._drop(cut)
                self._password_begun = True
                self._password_left -= cut
                items += self._scan(t_ns, first_new=len(self._buf), final=False)
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
        if (not first_new and len(data) <= SMALL_READ and not self._in_password
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
            if not self._in_password:
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
        if isinstance(self._buf, bytes):
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

    def _scan_slow(self, pos: int, final: bool) -> Scanned | None:
        """Identify the item at pos: (length, kind, reason), or None to wait for data.

        Scanners look only at the window of ``max_item`` bytes from pos.  That keeps
        every decision independent of how much data happens to be buffered: an item
        that cannot be decided within the window is cut as ``oversize`` whether the
        rest of it has arrived yet or not.
        """
        self._window = min(len(self._buf), pos + self.max_item)
        self._final = final
        if self._in_password:
            result = self._scan_password(pos, final)
        else:
            for scanner in _SCANNERS:
                result = scanner(self, pos)
                if result is not None:
                    break
            else:
                result = self._scan_garbage(pos, Unframed.GARBAGE)
        if isinstance(result, int):  # _NEED_MORE
            return self._wait_or_cut(pos, final)
        return result

    def _wait_or_cut(self, pos: int, final: bool) -> Scanned | None:
        """An item has begun but is incomplete: wait, unless the stream ended or it is too big."""
        pending = len(self._buf) - pos
        limit = self.max_image if self._is_image(pos) else self.max_item
        if pending >= limit:
            return limit, ItemKind.UNFRAMED, Unframed.OVERSIZE
        if final:
            return pending, ItemKind.UNFRAMED, Unframed.TRUNCATED
        return None

    def _scan_garbage(self, pos: int, reason: Unframed) -> Scan:
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

    def _scan_password(self, pos: int, final: bool) -> Scan:
        """The password: the line at pos, up to its line break or the header of a
        frame that completes.  Line breaks before it are items of their own; a
        line that begins with a frame header, or is longer than the password may
        be, is no password and is framed like any other bytes."""
        buf = self._buf
        if not self._password_begun:
            if buf[pos] in (0x0D, 0x0A):
                return self._scan_eol(pos)
            head = bytes(buf[pos:pos + 4])
            if head in FRAME_HEADERS:
                return self._no_password(pos, final)
            if len(head) < 4 and not final and any(h.startswith(head) for h in FRAME_HEADERS):
                return _NEED_MORE
        cut = self._password_cut(pos, final)
        if cut is None:
            return _NEED_MORE
        if cut <= pos:  # too long, or nothing (more) before the line's end
            return self._no_password(pos, final)
        self._in_password = self._password_mode = False
        return cut - pos, ItemKind.PASSWORD, None

    def _may_be_header(self, buf: bytes | bytearray) -> bool:
        """The line has not begun, and what came of it may still be a frame header."""
        return not self._password_begun and len(buf) < 4 and any(h.startswith(bytes(buf)) for h in FRAME_HEADERS)

    def _no_password(self, pos: int, final: bool) -> Scanned | None:
        self._in_password = self._password_mode = False
        return self._scan_slow(pos, final)

    def _password_cut(self, pos: int, final: bool) -> int | None:
        """Where the password from pos ends: at its first line break, or at the
        first header before it whose frame completes (one that never does is
        part of the password); -1 when that is past the bytes it may have;
        None while the bytes so far do not tell."""
        buf = self._buf
        n = len(buf)
        last = pos + self._password_left  # the latest it may end
        at = pos
        while (end := _PASSWORD_END.search(buf, at, min(n, last + 4))) is not None:
            i = end.start()
            if i > last:  # (a header at or before ``last`` would have come first)
                return -1
            if buf[i] in (0x0D, 0x0A):
                return i
            completes = self._frame_completes(i, final)
            if completes is None:
                return None
            if completes:
                return i
            at = i + 1
        if n > last + 3 or (final and n > last):
            return -1
        return n if final else None

    def _frame_completes(self, at: int, final: bool) -> bool | None:
        """Whether the frame whose header is at ``at`` completes (None: not yet known)."""
        window = self._window
        self._window = min(len(self._buf), at + self.max_item)
        result = (Framer._scan_sr1 if self._buf[at] == 0x73 else Framer._scan_text)(self, at)
        self._window = window
        if isinstance(result, int):  # _NEED_MORE
            return False if final or len(self._buf) - at >= self.max_item else None
        return result is not None and result[1] in _FRAMES

    # Each scanner returns None (not its kind of item), _NEED_MORE, or
    # (length, kind, reason).  They read only self._buf[pos:self._window].

    def _scan_text(self, pos: int) -> Scan:
        buf, window = self._buf, self._window
        head = bytes(buf[pos:pos + 4])
        if head not in (COMMAND_HEADER, RESPONSE_HEADER):
            begun = COMMAND_HEADER.startswith(head) or RESPONSE_HEADER.startswith(head)
            return _NEED_MORE if len(head) < 4 and begun else None
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

    def _scan_sr1(self, pos: int) -> Scan:
        buf, window = self._buf, self._window
        head = bytes(buf[pos:min(window, pos + 8)])
        if not head.startswith(CONFIG_HEADER):
            return _NEED_MORE if len(head) < 4 and CONFIG_HEADER.startswith(head) else None
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

    def _scan_set_config(self, pos: int, body: int, pad: int, trailer: bytes) -> Scan:
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

    def _scan_handshake(self, pos: int) -> Scan:
        buf, window = self._buf, self._window
        for word in HANDSHAKE_WORDS:
            if buf.startswith(word, pos, window):
                return len(word), ItemKind.HANDSHAKE, None
        tail = bytes(buf[pos:window])
        if any(len(tail) < len(w) and w.startswith(tail) for w in HANDSHAKE_WORDS):
            return _NEED_MORE
        return None

    def _scan_eol(self, pos: int) -> Scan:
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



def unasked(item: Item, max_item: int = DEFAULT_MAX_ITEM, max_image: int = DEFAULT_MAX_IMAGE) -> list[Item]:
    """A client's first line, cut as a password item, when no password was asked
    for: its bytes framed as any others (at the times the line came)."""
    framer = Framer(max_item, max_image)
    t0, t1 = item.t_start_ns, item.t_end_ns
    return [piece._replace(t_start_ns=t0, t_end_ns=t1) for piece in framer.feed(item.raw, t0) + framer.end(t1)]


_SCANNERS: tuple[Callable[[Framer, int], Scan], ...] = (
    Framer._scan_text, Framer._scan_sr1, Framer._scan_handshake,
    Framer._scan_eol, Framer._scan_jpeg, Framer._scan_png,
)
