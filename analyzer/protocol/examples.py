"""Small sessions that break each rule, and clean openings to build on.

One scenario per rule id: the (direction, bytes) steps of a session in which
that rule fires.  The tests check every rule against them, the violations
sample recording is made from them, and they are the shortest answer to
"what does this rule catch?".
"""

from __future__ import annotations

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.handshake import FAILED_VALIDATION, READYTOGO, SENDCHKPASS
from whiztap.analyzer.protocol.observations import Direction

C, S = Direction.C2S, Direction.S2C
Step = tuple[Direction, bytes]

CONFIG = encode(m.ConfigurationSettings((
    m.ChannelConfig(0), m.ChannelConfig(0), m.ChannelConfig(1, 0, 1), m.ChannelConfig(2),
)))  # ch0-1 servos, ch2 switch, ch3 sensor
WINSOCK_OPEN: list[Step] = [(S, SENDCHKPASS + b"\r\n"), (C, b"secret\r\n"), (S, READYTOGO + b"\r\n"),
                            (C, b"rr1-24--0--0-ss1"), (S, CONFIG)]
VPN_OPEN: list[Step] = [(C, b"rr1-24--0--0-ss1"), (S, CONFIG)]

SCENARIOS: dict[str, list[Step]] = {
    "PW-FRAME-GARBAGE": VPN_OPEN + [(C, b"\x00\x01junk rr1-0--5--0-ss1")],
    "PW-FRAME-TRUNCATED": VPN_OPEN + [(C, b"rr1-0--5")],
    "PW-FRAME-OVERSIZE": VPN_OPEN + [(C, b"sr1-25--" + b"\x01\x02\x03" * 30_000)],
    "PW-FRAME-EOL": VPN_OPEN + [(C, b"rr1-0--5--0-ss1\r\n")],
    "PW-SYNTAX-SPACE": VPN_OPEN + [(C, b"rr1-0-- 5--0-ss1")],
    "PW-SYNTAX-FIELDS": VPN_OPEN + [(C, b"rr1-0--5-ss1")],
    "PW-SYNTAX-LEADING-ZERO": VPN_OPEN + [(C, b"rr1-0--05--0-ss1")],
    "PW-SYNTAX-WIDTH": VPN_OPEN + [(C, b"rr1-0--12345--0-ss1")],
    "PW-DIRECTION": VPN_OPEN + [(S, b"rr1-0--5--0-ss1")],
    "PW-UNKNOWN-COMMAND": VPN_OPEN + [(C, b"rr1-0--0--7-ss1")],
    "PW-RANGE-CHANNEL": VPN_OPEN + [(C, b"rr1-31--5--0-ss1")],
    "PW-RANGE-SEND-VALUE": VPN_OPEN + [(C, b"rr1-0--2500--0-ss1")],
    "PW-RANGE-SCRIPT": VPN_OPEN + [(C, b"rr1-0--0--300-ss1")],
    "PW-FIXED-FIELD": VPN_OPEN + [(C, b"rr1-0--9--2-ss1")],
    "PW-RANGE-SENSOR": VPN_OPEN + [(C, b"rr1-3--0--0-ss1"), (S, b"cr1-3--1500--0-ss1")],
    "PW-RANGE-SERVO": VPN_OPEN + [(C, b"rr1-0--0--2-ss1"), (S, b"cr1-0--9000--0-ss1")],
    "PW-CFG-COUNT": [(C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x1a" + b"000" * 26 + b"-ss1")],
    "PW-CFG-DIGIT": [(C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x01a00-ss1")],
    "PW-CFG-UNIT": [(C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x01500-ss1")],
    "PW-CFG-UNUSED": [(C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x01010-ss1")],
    "PW-CFG-SWITCH-TYPE": [(C, b"rr1-24--0--0-ss1"), (S, b"sr1-\x01105-ss1")],
    "PW-SETCFG-FORM": VPN_OPEN + [(C, b"sr1-\x19\x0c\x00\x00\x0c0-ss1")],
    "PW-SETCFG-TRAILER": VPN_OPEN + [(C, b"sr1-\x19\x0c\x00\x00\x0cZ-ss1")],
    "PW-SETCFG-DEV": VPN_OPEN + [(C, b"sr1-25--\xc8\x00\x00\xc8--0-ss1")],
    "PW-SETCFG-PORT": VPN_OPEN + [(C, b"sr1-25--\x0c\x1e\x00\x0c--0-ss1")],
    "PW-SETCFG-UNIT": VPN_OPEN + [(C, b"sr1-25--\x0c\x01\x07\x0c--0-ss1")],
    "PW-SETCFG-CHECKSUM": VPN_OPEN + [(C, b"sr1-25--\x0c\x01\x00\x0d--0-ss1")],
    "PW-SETCFG-EMPTY": VPN_OPEN + [(C, b"sr1-25--\x00--0-ss1")],
    "PW-HS-ORDER": [(S, SENDCHKPASS), (S, READYTOGO)],
    "PW-HS-COMMAND-BEFORE-READY": [(S, SENDCHKPASS), (C, b"rr1-24--0--0-ss1")],
    "PW-HS-AFTER-FAILED": [(S, SENDCHKPASS), (C, b"wrong"), (S, FAILED_VALIDATION),
                           (C, b"rr1-24--0--0-ss1")],
    "PW-VPN-CONFIG-FIRST": [(C, b"rr1-0--0--2-ss1")],
    "PW-WINSOCK-CONFIG-FIRST": [(S, SENDCHKPASS), (C, b"pw"), (S, READYTOGO), (C, b"rr1-0--0--267-ss1")],
    "PW-UNIT-MISMATCH": VPN_OPEN + [(C, b"rr1-3--500--0-ss1")],
    "PW-CHANNEL-UNCONFIGURED": VPN_OPEN + [(C, b"rr1-9--0--2-ss1")],
    "PW-AMBIGUOUS": [(C, b"rr1-24--0--0-ss1"), (C, b"rr1-9--1--0-ss1")],
    "PW-PAIR-UNSOLICITED": VPN_OPEN + [(S, b"cr1-3--10--0-ss1")],
    "PW-PAIR-UNANSWERED": VPN_OPEN + [(C, b"rr1-0--0--2-ss1")],
}


