"""The Winsock handshake: its words, its transition table, and the mode it reveals.

A Winsock server asks for a password ('sendchkpass'), the client sends it, and
the server answers 'readytogo' or 'Failed Validation'; a VPN connection has no
handshake: its first command is Fetch Configuration Settings (docs/protocol.md).
The session feeds ``advance`` one step per item; the table says the next state,
the rule a step out of order breaks, and whether the step tells Winsock from VPN.

The three words are spelled here and nowhere else in whiztap: the framer, the
codec, the messages' titles, the password rule, the proxy in the middle, the
simulator and the Wireshark dissector all take them from here (a test holds
every library module to it).
"""

from __future__ import annotations

from enum import StrEnum

from whiztap.analyzer.protocol.rules import Violation

SENDCHKPASS = b"sendchkpass"  # the server asks for the password
READYTOGO = b"readytogo"  # the server took it
FAILED_VALIDATION = b"Failed Validation"  # the server refused it
VERDICTS = (READYTOGO, FAILED_VALIDATION)
HANDSHAKE_WORDS = (SENDCHKPASS, *VERDICTS)
"""Every word of the handshake, each an item of its own on the wire; only a server sends them."""


class Mode(StrEnum):
    UNKNOWN = "unknown"
    WINSOCK = "winsock"  # password handshake
    VPN = "vpn"  # no handshake: the first command is Fetch Configuration Settings


class HandshakeState(StrEnum):
    START = "start"
    EARLY_PASSWORD = "early_password"  # the client answered before it was asked
    AWAIT_PASSWORD = "await_password"
    AWAIT_VERDICT = "await_verdict"
    READY = "ready"
    FAILED = "failed"


class Step(StrEnum):
    """What the handshake state machine is fed."""

    SENDCHKPASS = "sendchkpass"
    PASSWORD = "password"
    READYTOGO = "readytogo"
    FAILED = "failed_validation"
    CLIENT_FRAME = "client_frame"
    SERVER_FRAME = "server_frame"


_S, _St = HandshakeState, Step
# (state, step) -> (next state, rule broken or None).  Pairs not listed keep the
# state and break PW-HS-ORDER (or PW-HS-AFTER-FAILED once validation failed).
HANDSHAKE_TABLE: dict[tuple[HandshakeState, Step], tuple[HandshakeState, str | None]] = {
    (_S.START, _St.SENDCHKPASS): (_S.AWAIT_PASSWORD, None),
    (_S.START, _St.CLIENT_FRAME): (_S.READY, None),  # VPN: no handshake
    (_S.START, _St.SERVER_FRAME): (_S.START, None),  # unsolicited: pairing reports it
    (_S.START, _St.PASSWORD): (_S.EARLY_PASSWORD, "PW-HS-ORDER"),  # an eager client
    (_S.EARLY_PASSWORD, _St.SENDCHKPASS): (_S.AWAIT_VERDICT, None),
    (_S.EARLY_PASSWORD, _St.CLIENT_FRAME): (_S.EARLY_PASSWORD, "PW-HS-COMMAND-BEFORE-READY"),
    (_S.AWAIT_PASSWORD, _St.PASSWORD): (_S.AWAIT_VERDICT, None),
    (_S.AWAIT_PASSWORD, _St.CLIENT_FRAME): (_S.AWAIT_PASSWORD, "PW-HS-COMMAND-BEFORE-READY"),
    (_S.AWAIT_PASSWORD, _St.READYTOGO): (_S.READY, "PW-HS-ORDER"),
    (_S.AWAIT_PASSWORD, _St.FAILED): (_S.FAILED, None),
    (_S.AWAIT_VERDICT, _St.READYTOGO): (_S.READY, None),
    (_S.AWAIT_VERDICT, _St.FAILED): (_S.FAILED, None),
    (_S.AWAIT_VERDICT, _St.CLIENT_FRAME): (_S.AWAIT_VERDICT, "PW-HS-COMMAND-BEFORE-READY"),
    (_S.READY, _St.CLIENT_FRAME): (_S.READY, None),
    (_S.READY, _St.SERVER_FRAME): (_S.READY, None),
}
# The transitions that tell the mode: the server asking for a password, or a
# client that starts with a command.
MODE_TOLD: dict[tuple[HandshakeState, Step], Mode] = {
    (_S.START, _St.SENDCHKPASS): Mode.WINSOCK,
    (_S.EARLY_PASSWORD, _St.SENDCHKPASS): Mode.WINSOCK,
    (_S.START, _St.CLIENT_FRAME): Mode.VPN,
}
EXPECTED_IN_STATE = {
    _S.START: "'sendchkpass' from the server or a first command from the client",
    _S.EARLY_PASSWORD: "'sendchkpass' from the server before the client's password",
    _S.AWAIT_PASSWORD: "the client's password",
    _S.AWAIT_VERDICT: "'readytogo' or 'Failed Validation' from the server",
    _S.READY: "commands and responses",
    _S.FAILED: "the connection to close",
}
STEP_WORDS = {
    _St.SENDCHKPASS: "'sendchkpass' from the server",
    _St.PASSWORD: "the client's password",
    _St.READYTOGO: "'readytogo' from the server",
    _St.FAILED: "'Failed Validation' from the server",
    _St.CLIENT_FRAME: "a command from the client",
    _St.SERVER_FRAME: "a frame from the server",
}
"""Each step in the words a rule's detail uses (the steps' values are identifiers)."""
_OUTCOME = {
    _S.START: "not started",
    _S.EARLY_PASSWORD: "password sent before 'sendchkpass'",
    _S.AWAIT_PASSWORD: "no password sent",
    _S.AWAIT_VERDICT: "no verdict",
    _S.READY: "readytogo",
    _S.FAILED: "failed validation",
}
SERVER_STEPS = {SENDCHKPASS: _St.SENDCHKPASS, READYTOGO: _St.READYTOGO, FAILED_VALIDATION: _St.FAILED}
"""The step each handshake word the server sends is."""


def advance(state: HandshakeState, step: Step) -> tuple[HandshakeState, Mode | None, Violation | None]:
    """The state after ``step``, the mode it tells (None: it tells none), and
    the rule it breaks (None: none)."""
    transition = HANDSHAKE_TABLE.get((state, step))
    if transition is None:
        rule: str | None = "PW-HS-AFTER-FAILED" if state is _S.FAILED else "PW-HS-ORDER"
        after = state
    else:
        after, rule = transition
    broken = None if rule is None else Violation(rule, f"got {STEP_WORDS[step]}, expected {EXPECTED_IN_STATE[state]}")
    return after, MODE_TOLD.get((state, step)), broken


def outcome(state: HandshakeState, mode: Mode) -> str:
    """How the handshake ended (or where it stands), for summaries."""
    return "none (vpn)" if mode is Mode.VPN else _OUTCOME[state]
