"""Every example frame of the Rev 1.8 spec, with the message it means.

These are the project's golden vectors.  Bracketed values in the spec are raw
bytes; the spaces the spec prints between Set Configuration triples are layout
and are not sent.
"""

from whiztap.analyzer.protocol import messages as m


def _config(count: int, digits: str) -> bytes:
    return b"sr1-" + bytes([count]) + digits.encode() + b"-ss1"


def _channels(pattern: str, count: int) -> tuple[m.ChannelConfig, ...]:
    unit, unused, switch = (int(c) for c in pattern)
    return tuple(m.ChannelConfig(unit, unused, switch) for _ in range(count))


SET_CONFIG_EXAMPLE = (
    b"sr1-25--"
    + bytes([12, 0, 0, 12, 1, 0, 12, 2, 0, 12, 3, 0, 12, 4, 0, 12, 5, 0])
    + bytes([72])
    + b"--0-ss1"
)

# Client to server: (wire bytes, every meaning the bytes can have).
COMMANDS: list[tuple[bytes, tuple]] = [
    (b"rr1-24--0--0-ss1", (m.FetchConfiguration(),)),
    (b"rr1-29--0--0-ss1", (m.FetchCameraImage(),)),
    (b"rr1-0--60--0-ss1", (m.NormalSend(0, 60),)),
    (b"rr1-2--72--0-ss1", (m.NormalSend(2, 72),)),
    (b"rr1-14--9--0-ss1", (m.NormalSend(14, 9),)),
    (b"rr1-0--1--0-ss1", (m.ActivateSwitch(0), m.NormalSend(0, 1))),
    (b"rr1-2--1--0-ss1", (m.ActivateSwitch(2), m.NormalSend(2, 1))),
    (b"rr1-14--1--0-ss1", (m.ActivateSwitch(14), m.NormalSend(14, 1))),
    (b"rr1-0--0--0-ss1", (m.SensorRequest(0), m.DeactivateSwitch(0), m.NormalSend(0, 0))),
    (b"rr1-2--0--0-ss1", (m.SensorRequest(2), m.DeactivateSwitch(2), m.NormalSend(2, 0))),
    (b"rr1-14--0--0-ss1", (m.SensorRequest(14), m.DeactivateSwitch(14), m.NormalSend(14, 0))),
    (b"rr1-3--0--0-ss1", (m.SensorRequest(3), m.DeactivateSwitch(3), m.NormalSend(3, 0))),
    (b"rr1-0--0--11-ss1", (m.PlayInternalScript(11),)),
    (b"rr1-0--0--23-ss1", (m.PlayInternalScript(23),)),
    (b"rr1-0--0--120-ss1", (m.PlayInternalScript(120),)),
    (b"rr1-0--0--267-ss1", (m.StopInternalScript(),)),
    (b"rr1-0--0--270-ss1", (m.PlayExternalScript(270),)),
    (b"rr1-0--0--272-ss1", (m.PlayExternalScript(272),)),
    (b"rr1-0--0--275-ss1", (m.PlayExternalScript(275),)),
    (b"rr1-0--0--269-ss1", (m.StopExternalScript(),)),
    (b"rr1-0--0--2-ss1", (m.ServoPositionRequest(0),)),
    (b"rr1-2--0--2-ss1", (m.ServoPositionRequest(2),)),
    (b"rr1-3--0--2-ss1", (m.ServoPositionRequest(3),)),
    (SET_CONFIG_EXAMPLE, (m.SetConfiguration(tuple(m.SetConfigEntry(12, p, 0) for p in range(6)), 72),)),
]

# Server to client.
RESPONSES: list[tuple[bytes, tuple]] = [
    (b"cr1-0--0--0-ss1", (m.ChannelResponse(0, 0),)),
    (b"cr1-2--100--0-ss1", (m.ChannelResponse(2, 100),)),
    (b"cr1-2--220--0-ss1", (m.ChannelResponse(2, 220),)),
    (_config(6, "000" * 6), (m.ConfigurationSettings(_channels("000", 6)),)),
    (_config(12, "001" * 12), (m.ConfigurationSettings(_channels("001", 12)),)),
    (_config(12, "200" * 12), (m.ConfigurationSettings(_channels("200", 12)),)),
    (_config(12, "101" * 12), (m.ConfigurationSettings(_channels("101", 12)),)),
]

HANDSHAKE_SERVER = [b"sendchkpass", b"readytogo", b"Failed Validation"]

ALL_FRAMES = [raw for raw, _ in COMMANDS + RESPONSES]
