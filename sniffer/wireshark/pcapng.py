"""A pcapng file of raw IP packets, written by hand, and the IP and TCP headers
that go into it.

Written by hand rather than with Scapy's ``PcapNgWriter``: the format is three
small block types, and building each packet as bytes is many times faster
than building Scapy packets, which matters for recordings of millions of reads.
Timestamps are kept to the nanosecond (``if_tsresol`` 9), as recordings have them.
"""

from __future__ import annotations

import ipaddress
import struct
from typing import IO, NamedTuple

LINKTYPE_RAW = 101  # raw IPv4 or IPv6, no link header: what tcpreasm calls DLT_RAW
MAX_PAYLOAD = 65535 - 20 - 20  # TCP payload one IPv4 packet can carry (IPv6 carries a little more)
FIN, SYN, RST, PSH, ACK = 0x01, 0x02, 0x04, 0x08, 0x10
WINDOW = 0xFFFF
WINDOW_SCALE = 14  # the largest: with it no recorded stream fills Wireshark's idea of the window
# SYN options: MSS, NOP, window scale (8 bytes, so the header stays a multiple of 4).
_SYN_OPTIONS = struct.pack("!BBHBBBB", 2, 4, MAX_PAYLOAD, 1, 3, 3, WINDOW_SCALE)

_SHB, _IDB, _EPB = 0x0A0D0D0A, 0x00000001, 0x00000006
_BYTE_ORDER_MAGIC = 0x1A2B3C4D
_OPT_COMMENT, _SHB_USERAPPL, _IF_NAME, _IF_TSRESOL = 1, 4, 2, 9


class Endpoint(NamedTuple):
    """One end of a TCP connection: a packed IPv4 or IPv6 address and a port."""

    address: bytes
    port: int

    @property
    def version(self) -> int:
        return 4 if len(self.address) == 4 else 6


def endpoint(host: str, port: int) -> Endpoint:
    """An endpoint from an address in text (``ValueError`` if it is none)."""
    return Endpoint(ipaddress.ip_address(host.strip("[]")).packed, port)


def _options(options: list[tuple[int, bytes]]) -> bytes:
    """pcapng options, each padded to 4 bytes, then the end of options."""
    if not options:
        return b""
    out = bytearray()
    for code, value in options:
        out += struct.pack("<HH", code, len(value)) + value + b"\0" * (-len(value) % 4)
    return bytes(out + b"\0\0\0\0")


def _block(block_type: int, body: bytes) -> bytes:
    length = 12 + len(body)
    return struct.pack("<II", block_type, length) + body + struct.pack("<I", length)


class PcapNgWriter:
    """Writes one section with one raw-IP interface to a binary stream."""

    def __init__(self, out: IO[bytes], application: str, comment: str = "") -> None:
        self.out = out
        self.packets = 0
        shb_options = [(_SHB_USERAPPL, application.encode())]
        if comment:
            shb_options.append((_OPT_COMMENT, comment.encode()))
        # version 1.0; the section length is unknown (-1): the file is written as a stream
        out.write(_block(_SHB, struct.pack("<IHHq", _BYTE_ORDER_MAGIC, 1, 0, -1) + _options(shb_options)))
        idb_options = [(_IF_NAME, b"whiztap"), (_IF_TSRESOL, b"\x09")]
        out.write(_block(_IDB, struct.pack("<HHI", LINKTYPE_RAW, 0, 0) + _options(idb_options)))

    def packet(self, t_ns: int, data: bytes, comment: str = "") -> None:
        """One Enhanced Packet Block: ``data`` (an IP packet) at ``t_ns``."""
        header = struct.pack("<IIIII", 0, (t_ns >> 32) & 0xFFFFFFFF, t_ns & 0xFFFFFFFF, len(data), len(data))
        options = _options([(_OPT_COMMENT, comment.encode())]) if comment else b""
        self.out.write(_block(_EPB, header + data + b"\0" * (-len(data) % 4) + options))
        self.packets += 1


def _checksum(data: bytes) -> int:
    """The Internet checksum (RFC 1071)."""
    if len(data) % 2:
        data += b"\0"
    total = sum(struct.unpack(f"!{len(data) // 2}H", data))
    while total >> 16:
        total = (total & 0xFFFF) + (total >> 16)
    return ~total & 0xFFFF


def tcp_packet(src: Endpoint, dst: Endpoint, seq: int, ack: int, flags: int, payload: bytes = b"",
               ip_id: int = 0) -> bytes:
    """An IPv4 or IPv6 packet holding one TCP segment, checksums right (Wireshark
    can check them), the window scale option on a SYN."""
    options = _SYN_OPTIONS if flags & SYN else b""
    offset = (20 + len(options)) // 4
    tcp = struct.pack("!HHIIBBHHH", src.port, dst.port, seq & 0xFFFFFFFF, ack & 0xFFFFFFFF if flags & ACK else 0,
                      offset << 4, flags, WINDOW, 0, 0) + options + payload
    length = len(tcp)
    if src.version == 4:
        pseudo = src.address + dst.address + struct.pack("!BBH", 0, 6, length)
    else:
        pseudo = src.address + dst.address + struct.pack("!IxxxB", length, 6)
    tcp = tcp[:16] + struct.pack("!H", _checksum(pseudo + tcp)) + tcp[18:]
    if src.version == 4:
        ip = struct.pack("!BBHHHBBH4s4s", 0x45, 0, 20 + length, ip_id & 0xFFFF, 0x4000, 64, 6, 0,
                         src.address, dst.address)
        return ip[:10] + struct.pack("!H", _checksum(ip)) + ip[12:] + tcp
    return struct.pack("!IHBB16s16s", 6 << 28, length, 6, 64, src.address, dst.address) + tcp
