"""Every conformance check whiztap makes, with a stable id.

Ids are part of the interface: reports, ``--ignore`` and CI configurations name
them, so an id is never renamed or reused.
"""

from __future__ import annotations

from dataclasses import dataclass

from whiztap.analyzer.protocol.text import LowerNamed


class Severity(LowerNamed):
    INFO = 1
    WARNING = 2
    ERROR = 3

    @classmethod
    def parse(cls, text: str) -> Severity:
        try:
            return cls[text.upper()]
        except KeyError:
            raise ValueError(f"unknown severity {text!r}: expected info, warning or error") from None


@dataclass(frozen=True, slots=True)
class Rule:
    id: str
    severity: Severity
    section: str  # the spec section the rule comes from
    summary: str  # one line: what the spec requires


@dataclass(frozen=True, slots=True)
class Violation:
    rule_id: str
    detail: str  # what was expected and what was seen
    where: str = ""  # the spec section of the message it was broken in, when not the rule's own

    @property
    def rule(self) -> Rule:
        return RULES[self.rule_id]

    @property
    def section(self) -> str:
        """The spec section a report cites: the message's own for a rule that
        holds in several messages (a Servo Position Request's channel out of
        range is in the Servo Position Request's section, not the Normal
        Send's the rule names), else the rule's."""
        return self.where or RULES[self.rule_id].section

    @property
    def severity(self) -> Severity:
        return RULES[self.rule_id].severity


E, W, N = Severity.ERROR, Severity.WARNING, Severity.INFO  # N: a note
_MSG = "API Message Descriptions"
_FLOW = "Functional Flow"

RULES: dict[str, Rule] = {
    r.id: r
    for r in (
        # framing and syntax
        Rule("PW-FRAME-GARBAGE", E, _MSG, "Every byte on the wire belongs to a frame or handshake message"),
        Rule("PW-FRAME-TRUNCATED", E, _MSG, "A frame that was started is completed with its trailer"),
        Rule("PW-FRAME-OVERSIZE", E, _MSG, "No frame is longer than the analyzer's size limit"),
        Rule("PW-FRAME-EOL", N, _MSG, "Frames are not followed by line breaks (only handshake text may be)"),
        Rule("PW-SYNTAX-SPACE", E, _MSG, "No spaces are allowed in a message"),
        Rule("PW-SYNTAX-FIELDS", E, _MSG, "A frame body is three decimal fields separated by '--'"),
        Rule("PW-SYNTAX-LEADING-ZERO", W, _MSG, "Numbers are written without leading zeros"),
        Rule("PW-SYNTAX-WIDTH", E, _MSG, "A field is no wider than the message's Layout allows"),
        Rule("PW-DIRECTION", E, "API Definition", "Each message kind travels in its own direction only"),
        Rule("PW-UNKNOWN-COMMAND", E, _MSG, "A command's codes match one of the spec's commands"),
        # fields and ranges
        Rule("PW-RANGE-CHANNEL", E, "Normal Send to Channel/Port", "Channel numbers are 0 to 23"),
        Rule("PW-RANGE-SEND-VALUE", E, "Normal Send to Channel/Port", "Normal Send values are 0 to 2000"),
        Rule("PW-RANGE-SCRIPT", E, "Play Internal Script",
             "Script numbers are 11-266 (internal) or 270-275 (external); 267 and 269 stop them"),
        Rule("PW-FIXED-FIELD", E, _MSG, "Fields with a fixed value carry that value (for example Data3 = 0)"),
        Rule("PW-RANGE-SENSOR", E, "Sensor/Servo Response", "Sensor data is 0 to 1024"),
        Rule("PW-RANGE-SERVO", E, "Sensor/Servo Response", "Servo data is 0 to 8000 (position = data / 4)"),
        Rule("PW-CFG-COUNT", E, "Configuration Settings", "The channel count is at most 24 (channels 0 to 23)"),
        Rule("PW-CFG-DIGIT", E, "Configuration Settings", "Each per-channel value is one ASCII digit"),
        Rule("PW-CFG-UNIT", E, "Configuration Settings", "Unit type is 0 (servo), 1 (switch) or 2 (sensor)"),
        Rule("PW-CFG-UNUSED", W, "Configuration Settings", "The unused per-channel field is 0"),
        Rule("PW-CFG-SWITCH-TYPE", E, "Configuration Settings", "Switch type is 0 or 1"),
        Rule("PW-SETCFG-FORM", E, "Set Configuration Settings",
             "Data1 is written as the text '25' followed by '--', as in the spec's example"),
        Rule("PW-SETCFG-TRAILER", E, "Set Configuration Settings", "The checksum byte is followed by '--0-ss1'"),
        Rule("PW-SETCFG-DEV", E, "Set Configuration Settings", "Dev# is 0 to 127"),
        Rule("PW-SETCFG-PORT", E, "Set Configuration Settings", "Port# is 0 to 23"),
        Rule("PW-SETCFG-UNIT", E, "Set Configuration Settings", "Unit type is 0 (servo), 1 (switch) or 2 (sensor)"),
        Rule("PW-SETCFG-CHECKSUM", E, "Set Configuration Settings", "The checksum byte matches the entries"),
        Rule("PW-SETCFG-EMPTY", W, "Set Configuration Settings", "A Set Configuration carries at least one entry"),
        # session flow
        Rule("PW-HS-ORDER", E, _FLOW,
             "Winsock handshake order: sendchkpass, password, then readytogo or Failed Validation"),
        Rule("PW-HS-COMMAND-BEFORE-READY", E, _FLOW, "The client sends no command before 'readytogo'"),
        Rule("PW-HS-AFTER-FAILED", E, _FLOW, "Nothing but closing follows 'Failed Validation'"),
        Rule("PW-VPN-CONFIG-FIRST", E, _FLOW,
             "Without a password handshake (VPN), the first command is Fetch Configuration Settings"),
        Rule("PW-WINSOCK-CONFIG-FIRST", W, _FLOW,
             "After 'readytogo' the client first requests the Configuration Settings"),
        Rule("PW-UNIT-MISMATCH", E, "Configuration Settings",
             "A command fits the unit type configured on its channel"),
        Rule("PW-CHANNEL-UNCONFIGURED", W, "Configuration Settings",
             "Commands address channels the server's configuration lists"),
        Rule("PW-AMBIGUOUS", N, _MSG,
             "The frame has several meanings and no channel configuration was seen to choose one"),
        Rule("PW-PAIR-UNSOLICITED", E, "API Definition", "Every response answers an outstanding request"),
        Rule("PW-PAIR-UNANSWERED", E, "API Definition", "Every request that has a response gets one"),
    )
}
