"""A Scapy layer for the Progwhiz protocol, for people who dissect with Scapy.

    >>> from whiztap.sniffer.record.scapy_layer import Progwhiz, bind
    >>> bind(5000)
    >>> pkts = rdpcap("session.pcap")   # each TCP payload to or from port 5000 is Progwhiz
    >>> pkts[5][Progwhiz].items()

The protocol is a byte stream, so one TCP segment may hold several frames or
part of one: the layer frames each payload on its own (``items()``), which is
right for the usual one-frame-per-segment traffic.  For whole streams, use
``whiztap capture``, which reassembles TCP first.  ``bind`` binds both ports,
source and destination, so replies dissect as well as requests.
"""

from __future__ import annotations

from scapy.fields import StrField
from scapy.layers.inet import TCP
from scapy.packet import Packet, bind_bottom_up, bind_layers

from whiztap.analyzer.protocol.codec import decode
from whiztap.analyzer.protocol.framing import Framer, Item
from whiztap.analyzer.protocol.text import escape


class Progwhiz(Packet):
    name = "Progwhiz"
    fields_desc = [StrField("data", b"")]

    def items(self) -> list[Item]:
        """The payload cut into framer items (frames, handshake text, unframed bytes)."""
        framer = Framer()
        return framer.feed(bytes(self.data), 0) + framer.end(0)

    def describe_items(self) -> list[str]:
        out = []
        for item in self.items():
            message = decode(item.kind, item.raw, item.reason).message
            out.append(message.describe() if message is not None else f"{item.kind} {escape(item.raw[:40])}")
        return out

    def mysummary(self) -> str:
        return "Progwhiz " + "; ".join(self.describe_items())


def bind(port: int = 5000) -> None:
    """Dissect TCP payloads to and from ``port`` as Progwhiz."""
    bind_bottom_up(TCP, Progwhiz, dport=port)
    bind_bottom_up(TCP, Progwhiz, sport=port)
    bind_layers(TCP, Progwhiz, dport=port)
