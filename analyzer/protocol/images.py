"""Camera pictures in a stream: JPEG walked segment by segment, PNG chunk by chunk.

The framer's image scanners (docs/protocol.md, *Framing*), as a mixin of
``framing.Framer``: they read the framer's buffer and window and keep
``_resume``, where the walk of a picture still arriving at the start of the
buffer goes on, so a large picture in many reads is walked once.
"""

from __future__ import annotations

from whiztap.analyzer.protocol.items import NEED_MORE, ItemKind, Scan, Unframed

JPEG_SOI = b"\xff\xd8\xff"
PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


class ImageScanning:
    """The image part of ``Framer``; every attribute it reads is the framer's."""

    _buf: bytearray | bytes
    _window: int
    _final: bool
    _resume: tuple[int, int] | None
    max_item: int
    max_image: int

    def _scan_garbage(self, pos: int, reason: Unframed) -> Scan:  # the framer's
        raise NotImplementedError

    def _image_pending(self) -> bool:
        """Whether the image at the start of the buffer still needs more bytes
        (looking only at what arrived since the last look)."""
        self._window = min(len(self._buf), self.max_item)
        self._final = False
        scanner = ImageScanning._scan_jpeg if self._buf[0] == 0xFF else ImageScanning._scan_png
        return len(self._buf) < self.max_image and scanner(self, 0) == NEED_MORE

    def _is_image(self, pos: int) -> bool:
        buf = self._buf
        return buf.startswith(JPEG_SOI, pos) or buf.startswith(PNG_SIGNATURE, pos)

    def _in_partial_png(self, pos: int, at: int) -> bool:
        """Whether the sync point at ``at`` lies inside the start of a PNG signature
        that the data so far ends in (the signature holds CR and LF itself)."""
        buf, window = self._buf, self._window
        if self._final or window - pos >= self.max_item or buf[at] not in (0x0D, 0x0A):
            return False
        start = buf.rfind(b"\x89", max(pos + 1, at - len(PNG_SIGNATURE) + 1), at)
        return start != -1 and PNG_SIGNATURE.startswith(bytes(buf[start:window]))

    def _image_start(self, pos: int, signature: bytes) -> int | None:
        """None (no image opening with ``signature`` at pos), NEED_MORE, or the end of its max_image window."""
        n = min(len(self._buf), pos + self.max_image)
        head = bytes(self._buf[pos:min(n, pos + len(signature))])
        if not head or not signature.startswith(head):
            return None
        return NEED_MORE if len(head) < len(signature) else n

    def _scan_jpeg(self, pos: int) -> Scan:
        n = self._image_start(pos, JPEG_SOI)
        if n is None or n == NEED_MORE:
            return n
        phase, i = self._resume if pos == 0 and self._resume is not None else (0, pos + 2)
        result = self._walk_jpeg(pos, n, phase, i) if phase == 0 else self._walk_entropy(pos, n, i)
        if result != NEED_MORE:
            self._resume = None
        return result

    def _walk_jpeg(self, pos: int, n: int, phase: int, i: int) -> Scan:
        buf = self._buf
        # Marker segments up to Start Of Scan carry their own lengths.
        while True:
            if i + 2 > n:
                self._resume = (0, i) if pos == 0 else None
                return NEED_MORE
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
                    return NEED_MORE
                seg_len = (buf[i + 2] << 8) | buf[i + 3]
                if seg_len < 2:
                    return self._scan_garbage(pos, Unframed.GARBAGE)
                i += 2 + seg_len
                if marker == 0xDA:
                    return self._walk_entropy(pos, n, i)

    def _walk_entropy(self, pos: int, n: int, i: int) -> Scan:
        """Entropy-coded data: FF is stuffed as FF 00; FF D0-D7 are restarts; any
        other marker (a further scan's tables) carries a length again."""
        buf = self._buf
        while True:
            j = buf.find(b"\xff", i, n)
            if j == -1 or j + 1 >= n:
                self._resume = (1, n if j == -1 else j) if pos == 0 else None
                return NEED_MORE
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
                    return NEED_MORE
                i = j + 2 + ((buf[j + 2] << 8) | buf[j + 3])

    def _scan_png(self, pos: int) -> Scan:
        n = self._image_start(pos, PNG_SIGNATURE)
        if n is None or n == NEED_MORE:
            return n
        buf = self._buf
        i = self._resume[1] if pos == 0 and self._resume is not None else pos + 8
        while True:
            if i + 8 > n:
                self._resume = (2, i) if pos == 0 else None
                return NEED_MORE
            length = int.from_bytes(buf[i:i + 4], "big")
            ctype = bytes(buf[i + 4:i + 8])
            if not ctype.isalpha():
                self._resume = None
                return self._scan_garbage(pos, Unframed.GARBAGE)
            if ctype == b"IEND":
                end = i + 12 + length
                if end > n:
                    self._resume = (2, i) if pos == 0 else None
                    return NEED_MORE
                self._resume = None
                return end - pos, ItemKind.IMAGE, None
            i += 12 + length
