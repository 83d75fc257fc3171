"""Stream builders shared by the framing, codec and session tests."""

from itertools import pairwise

from hypothesis import strategies as st

from whiztap.analyzer.protocol.framing import DEFAULT_MAX_IMAGE, DEFAULT_MAX_ITEM, Framer, Item
from tests.spec_vectors import ALL_FRAMES, HANDSHAKE_SERVER

# Smallest byte streams the framer accepts as images: structure only.
TINY_JPEG = (
    b"\xff\xd8"  # SOI
    + b"\xff\xe0\x00\x06JFIF"  # APP0, 4 payload bytes
    + b"\xff\xda\x00\x04\x01\x02"  # SOS, 2 payload bytes
    + b"\x12\xff\x00\x34\xff\xd3\x56"  # entropy data with a stuffed FF and a restart
    + b"\xff\xd9"  # EOI
)
TINY_PNG = (
    b"\x89PNG\r\n\x1a\n"
    + b"\x00\x00\x00\x02IHDR" + b"ab" + b"\x00\x00\x00\x00"
    + b"\x00\x00\x00\x00IEND" + b"\xaeB`\x82"
)


def big_jpeg(size: int, seed: int = 0) -> bytes:
    """A JPEG-shaped stream of about ``size`` bytes: long APP segments, then
    entropy data holding stuffed FF 00 pairs and restarts."""
    out = bytearray(b"\xff\xd8")
    header = min(size // 2, 3 * 65533)
    while header > 0:
        n = min(header, 65533)
        out += b"\xff\xe1" + (n + 2).to_bytes(2, "big") + bytes((seed + i) % 251 for i in range(n))
        header -= n
    out += b"\xff\xda\x00\x04\x01\x02"
    body = bytearray((seed * 7 + i * 13) % 255 for i in range(max(size - len(out) - 2, 0)))
    body[::997] = b"\xff" * len(body[::997])  # every 997th byte an FF: stuffed or a restart
    for i in range(0, len(body), 997):
        if i + 1 < len(body):
            body[i + 1] = 0x00 if (i // 997) % 2 else 0xD3
    return bytes(out + body + b"\xff\xd9")


def frame_all(chunks: list[bytes], max_item: int | None = None, max_image: int | None = None) -> list[Item]:
    framer = Framer(max_item or DEFAULT_MAX_ITEM, max_image or DEFAULT_MAX_IMAGE)
    items: list[Item] = []
    for t, chunk in enumerate(chunks):
        items += framer.feed(chunk, t)
    return items + framer.end(len(chunks))


def chunked(data: bytes, cuts: list[int]) -> list[bytes]:
    points = sorted({c % (len(data) + 1) for c in cuts} | {0, len(data)})
    return [data[a:b] for a, b in pairwise(points) if b > a]


def stream_pieces():
    """Frames, handshake text, images, line breaks, and hostile fragments."""
    piece = st.one_of(
        st.sampled_from(ALL_FRAMES),
        st.sampled_from(HANDSHAKE_SERVER),
        st.sampled_from([TINY_JPEG, TINY_PNG, b"\r\n", b"\n", b"\r"]),
        st.sampled_from([b"rr1-", b"sr1-", b"sr1-25--", b"-ss1", b"--0-ss1", b"\xff\xd8\xff", b"\x89PNG",
                         b"readyto", b"sr1-\x19", b"cr1-9--"]),
        st.binary(max_size=40),
        st.builds(lambda n, body: b"sr1-" + bytes([n]) + body + b"-ss1",
                  st.integers(0, 30), st.binary(max_size=100)),
        st.builds(lambda body, chk: b"sr1-25--" + body + bytes([chk]) + b"--0-ss1",
                  st.binary(max_size=30), st.integers(0, 255)),
    )
    return st.lists(piece, max_size=40)
