"""The sans-IO robot: handshake, every command, state over time, malformed input.

No sockets: bytes and times go in, replies and notes come out, so every split of
every frame can be tried exactly.
"""

from __future__ import annotations

import logging
import re

import pytest

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import UNIT_OF_COMMAND, encode
from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Session
from whiztap.sniffer.sim.camera import render_frame
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, ChannelSpecError, format_channels, parse_channels
from whiztap.sniffer.sim.robot import Output, Robot, ServerMode
from whiztap.sniffer.sim.waveforms import SHAPES, Noise, Ramp, Sine, make_signal
from tests.spec_vectors import COMMANDS, HANDSHAKE_SERVER, RESPONSES, SET_CONFIG_EXAMPLE

SEC = 1_000_000_000
PASSWORD = b"s3cret!"

# Every meaning of every example command of the spec: the simulator must carry out
# each one when the channel's unit gives the frame that meaning.
EXAMPLES = [(raw, message) for raw, meanings in COMMANDS for message in meanings]
SERVER_EXAMPLES = [raw for raw, _ in RESPONSES] + HANDSHAKE_SERVER


def fake_camera(frame: int, t_s: float) -> bytes:
    """A tiny JPEG-shaped stream (SOI, a comment naming the frame, a scan, EOI): cheap and framable."""
    text = b"frame %d at %.3f s" % (frame, t_s)
    comment = b"\xff\xfe" + (len(text) + 2).to_bytes(2, "big") + text
    scan = b"\xff\xda\x00\x08\x01\x01\x00\x00\x3f\x00" + b"\x12\x34"
    return b"\xff\xd8" + comment + scan + b"\xff\xd9"


def make_robot(channels: str = DEFAULT_CHANNELS, **kwargs) -> Robot:
    kwargs.setdefault("camera", fake_camera)
    return Robot(parse_channels(channels), **kwargs)


def example_robot(message: m.Message) -> Robot:
    """A robot on which the example frame means ``message``."""
    unit = UNIT_OF_COMMAND.get(type(message))
    robot = make_robot(f"{unit}:0-23" if unit is not None else "sensor:0-23")
    if isinstance(message, m.DeactivateSwitch):
        robot.switches = [True] * len(robot.switches)
    robot.internal_script = 11 if isinstance(message, m.StopInternalScript) else None
    robot.external_script = 270 if isinstance(message, m.StopExternalScript) else None
    return robot


def check_effect(message: m.Message, robot: Robot, replies: list[bytes], t: int) -> None:
    """What the message must do to the robot, and what it answers."""
    match message:
        case m.FetchConfiguration():
            assert replies == [encode(robot.configuration())]
        case m.FetchCameraImage():
            assert replies == [fake_camera(1, t / SEC)]
        case m.SensorRequest(channel=ch):
            assert replies == [b"cr1-%d--%d--0-ss1" % (ch, robot.sensor_value(ch, t))]
        case m.ServoPositionRequest(channel=ch):
            assert replies == [b"cr1-%d--4000--0-ss1" % ch]  # centred: position 1000, data 4000
        case m.NormalSend(channel=ch, value=value):
            assert replies == [] and robot.servo_target(ch) == value
        case m.ActivateSwitch(channel=ch):
            assert replies == [] and robot.switches[ch] and sum(robot.switches) == 1
        case m.DeactivateSwitch(channel=ch):
            assert replies == [] and not robot.switches[ch] and sum(robot.switches) == len(robot.switches) - 1
        case m.PlayInternalScript(script=n):
            assert replies == [] and robot.internal_script == n
        case m.PlayExternalScript(script=n):
            assert replies == [] and robot.external_script == n
        case m.StopInternalScript():
            assert replies == [] and robot.internal_script is None
        case m.StopExternalScript():
            assert replies == [] and robot.external_script is None
        case m.SetConfiguration():
            assert replies == [] and format_channels(robot.channels) == "servo:0-5,sensor:6-23"
        case _:
            raise AssertionError(f"no expectation for {message}")


def fields(frame: bytes) -> tuple[int, int, int]:
    found = re.fullmatch(rb"[rc]r1-(\d+)--(\d+)--(\d+)-ss1", frame)
    assert found is not None
    return int(found[1]), int(found[2]), int(found[3])


def data(out: Output) -> list[bytes]:
    return [r.data for r in out.replies]


def rule_ids(out: Output) -> list[str | None]:
    return [n.rule_id for n in out.notes if n.level >= logging.INFO and n.rule_id]


# -- channel notation ---------------------------------------------------------------------


def test_default_channels_cover_every_unit_and_both_switch_types():
    channels = parse_channels(DEFAULT_CHANNELS)
    assert len(channels) == 24
    assert {c.unit_type for c in channels} == {0, 1, 2}
    assert {c.switch_type for c in channels if c.unit_type == 1} == {0, 1}
    assert format_channels(channels) == DEFAULT_CHANNELS


@pytest.mark.parametrize("spec, expected", [
    ("servo:0-2", (m.ChannelConfig(0),) * 3),
    ("sensor:1, servo:0", (m.ChannelConfig(0), m.ChannelConfig(2))),
    ("switch1:0,switch0:1", (m.ChannelConfig(1, 0, 1), m.ChannelConfig(1, 0, 0))),
])
def test_parse_channels(spec, expected):
    assert parse_channels(spec) == expected


@pytest.mark.parametrize("spec, message", [
    ("", "no channels"),
    ("servo:0-3,sensor:3", "channel 3 is given twice"),
    ("servo:0-3,sensor:5", "channel 4 has no unit"),
    ("motor:0-3", "bad channel group"),
    ("servo", "bad channel group"),
    ("servo:a-b", "bad channel range"),
    ("servo:5-2", "bad channel range"),
    ("servo:0-24", "at most 24 channels"),
])
def test_parse_channels_rejects(spec, message):
    with pytest.raises(ChannelSpecError, match=message):
        parse_channels(spec)


# -- winsock handshake ----------------------------------------------------------------------


def test_winsock_greets_with_sendchkpass_and_vpn_says_nothing():
    robot = make_robot()
    assert data(robot.connect(ServerMode.WINSOCK, PASSWORD).start(0)) == [b"sendchkpass"]
    assert data(robot.connect(ServerMode.VPN).start(0)) == []


@pytest.mark.parametrize("suffix", [b"", b"\r", b"\n", b"\r\n"])
def test_password_split_at_every_offset(suffix):
    stream = PASSWORD + suffix + b"rr1-24--0--0-ss1"
    for cut in range(1, len(stream)):
        robot = make_robot()
        conn = robot.connect(ServerMode.WINSOCK, PASSWORD)
        first, second = conn.receive(stream[:cut], 1), conn.receive(stream[cut:], 2)
        assert data(first) + data(second) == [b"readytogo", encode(robot.configuration())], cut
        assert (b"readytogo" in data(first)) == (cut >= len(PASSWORD))
        assert not first.close and not second.close
        assert all(n.level < logging.WARNING for n in first.notes + second.notes)


def test_password_byte_by_byte():
    robot = make_robot()
    conn = robot.connect(ServerMode.WINSOCK, PASSWORD)
    replies = [r for b in PASSWORD + b"\r\nrr1-24--0--0-ss1" for r in data(conn.receive(bytes([b]), 1))]
    assert replies == [b"readytogo", encode(robot.configuration())]


@pytest.mark.parametrize("wrong", [b"x", b"s3cX", b"S3cret!", b"rr1-24--0--0-ss1", b"\r\n" + PASSWORD])
def test_wrong_password_fails_validation_and_closes(wrong):
    conn = make_robot().connect(ServerMode.WINSOCK, PASSWORD)
    out = conn.receive(wrong, 1)
    assert data(out) == [b"Failed Validation"] and out.close
    later = conn.receive(PASSWORD + b"rr1-24--0--0-ss1", 2)
    assert data(later) == [] and not later.close


def test_wrong_password_is_judged_at_the_first_wrong_byte():
    conn = make_robot().connect(ServerMode.WINSOCK, PASSWORD)
    assert data(conn.receive(PASSWORD[:3], 1)) == []
    assert data(conn.receive(b"?", 2)) == [b"Failed Validation"]


def test_nothing_is_served_before_the_password_is_complete():
    robot = make_robot()
    conn = robot.connect(ServerMode.WINSOCK, PASSWORD)
    assert data(conn.receive(PASSWORD[:-1], 1)) == []
    assert conn.state == "await_password"
    assert data(conn.receive(PASSWORD[-1:] + b"rr1-12--0--0-ss1", 2)) == [
        b"readytogo", b"cr1-12--%d--0-ss1" % robot.sensor_value(12, 2)]


def test_winsock_needs_a_password():
    with pytest.raises(ValueError):
        make_robot().connect(ServerMode.WINSOCK, b"")


# -- the spec's examples -----------------------------------------------------------------------


@pytest.mark.parametrize("frame, message", EXAMPLES, ids=[f"{f.decode('latin-1')}={type(msg).__name__}"
                                                         for f, msg in EXAMPLES])
def test_spec_example_split_at_every_offset(frame, message):
    t = 3 * SEC
    for cut in range(len(frame) + 1):
        robot = example_robot(message)
        conn = robot.connect(ServerMode.VPN)
        first = conn.receive(frame[:cut], t)
        if cut < len(frame):
            assert data(first) == [], "nothing may happen before the frame is complete"
        second = conn.receive(frame[cut:], t)
        check_effect(message, robot, data(first) + data(second), t)
        assert not rule_ids(first) + rule_ids(second)


def test_spec_examples_one_byte_at_a_time_on_one_connection():
    robot = make_robot("servo:0-23")
    conn = robot.connect(ServerMode.VPN)
    stream = b"rr1-0--0--2-ss1rr1-2--0--2-ss1rr1-3--0--2-ss1rr1-24--0--0-ss1"
    replies = [r for i in range(len(stream)) for r in data(conn.receive(stream[i:i + 1], SEC))]
    assert replies == [b"cr1-0--4000--0-ss1", b"cr1-2--4000--0-ss1", b"cr1-3--4000--0-ss1",
                       encode(robot.configuration())]


@pytest.mark.parametrize("frame", SERVER_EXAMPLES)
def test_server_examples_sent_by_a_client_are_logged_and_ignored(frame):
    robot = make_robot()
    conn = robot.connect(ServerMode.VPN)
    out = conn.receive(frame + b"rr1-24--0--0-ss1", SEC)
    assert data(out) == [encode(robot.configuration())]
    assert rule_ids(out) == ["PW-DIRECTION"]


# -- meaning by channel unit ---------------------------------------------------------------------


def test_ambiguous_frames_take_the_meaning_of_the_channel_unit():
    robot = make_robot("servo:0,switch:1,sensor:2")
    conn = robot.connect(ServerMode.VPN)
    assert data(conn.receive(b"rr1-0--0--0-ss1", SEC)) == []  # Normal Send 0
    assert robot.servo_target(0) == 0
    assert data(conn.receive(b"rr1-0--1--0-ss1", SEC)) == []  # Normal Send 1
    assert robot.servo_target(0) == 1
    conn.receive(b"rr1-1--1--0-ss1", SEC)
    assert robot.switches[1]
    conn.receive(b"rr1-1--0--0-ss1", SEC)
    assert not robot.switches[1]
    assert data(conn.receive(b"rr1-2--0--0-ss1", SEC)) == [b"cr1-2--%d--0-ss1" % robot.sensor_value(2, SEC)]


@pytest.mark.parametrize("frame, rule", [
    (b"rr1-2--1--0-ss1", "PW-UNIT-MISMATCH"),  # a sensor cannot be switched on
    (b"rr1-2--0--2-ss1", "PW-UNIT-MISMATCH"),  # a sensor has no servo position
    (b"rr1-1--500--0-ss1", "PW-UNIT-MISMATCH"),  # a switch is not a servo
    (b"rr1-3--0--0-ss1", "PW-CHANNEL-UNCONFIGURED"),
    (b"rr1-30--0--0-ss1", "PW-RANGE-CHANNEL"),
    (b"rr1-0--2001--0-ss1", "PW-RANGE-SEND-VALUE"),
    (b"rr1-0--0--268-ss1", "PW-RANGE-SCRIPT"),
    (b"rr1-0--0--5-ss1", "PW-UNKNOWN-COMMAND"),
    (b"rr1-24--3--0-ss1", "PW-FIXED-FIELD"),
    (b"rr1-0--0 --2-ss1", "PW-SYNTAX-SPACE"),
    (b"rr1-a--0--2-ss1", "PW-SYNTAX-FIELDS"),
    (b"hello", "PW-FRAME-GARBAGE"),
    (b"rr1-0--0--2rr1-", "PW-FRAME-TRUNCATED"),
])
def test_bad_commands_are_logged_with_their_rule_and_ignored(frame, rule):
    robot = make_robot("servo:0,switch:1,sensor:2")
    conn = robot.connect(ServerMode.VPN)
    out = conn.receive(frame, SEC)
    assert data(out) == [] and not out.close
    # the connection still serves (and garbage is known for garbage once a frame follows it)
    tail = conn.receive(b"0--0--2-ss1" if frame.endswith(b"rr1-") else b"rr1-0--0--2-ss1", SEC)
    assert data(tail) == [b"cr1-0--4000--0-ss1"]
    assert rule in rule_ids(out) + rule_ids(tail)
    assert robot.servo_target(0) == 1000 and not any(robot.switches)


def test_leading_zero_is_noted_but_served():
    robot = make_robot("servo:0-5")
    out = robot.connect(ServerMode.VPN).receive(b"rr1-05--0--2-ss1", SEC)
    assert data(out) == [b"cr1-5--4000--0-ss1"]
    assert rule_ids(out) == ["PW-SYNTAX-LEADING-ZERO"]


def test_line_breaks_between_frames_are_ignored_quietly():
    robot = make_robot()
    out = robot.connect(ServerMode.VPN).receive(b"rr1-0--0--2-ss1\r\nrr1-1--0--2-ss1\n", SEC)
    assert data(out) == [b"cr1-0--4000--0-ss1", b"cr1-1--4000--0-ss1"]
    assert all(n.level == logging.DEBUG for n in out.notes)


def test_a_frame_cut_off_by_the_client_closing_is_logged():
    conn = make_robot().connect(ServerMode.VPN)
    assert data(conn.receive(b"rr1-12--0", SEC)) == []
    assert rule_ids(conn.end(SEC)) == ["PW-FRAME-TRUNCATED"]


# -- servos and scripts ------------------------------------------------------------------------------


def servo_data(conn, channel: int, t: int) -> int:
    [reply] = data(conn.receive(b"rr1-%d--0--2-ss1" % channel, t))
    return fields(reply.replace(b"cr1-", b"rr1-"))[1]


def test_servo_travels_towards_the_commanded_position_at_its_speed():
    robot = make_robot(servo_speed=500)
    conn = robot.connect(ServerMode.VPN)
    conn.receive(b"rr1-3--1500--0-ss1", 10 * SEC)
    assert servo_data(conn, 3, 10 * SEC) == 4000
    assert servo_data(conn, 3, 10 * SEC + SEC // 2) == 1250 * 4
    assert servo_data(conn, 3, 11 * SEC) == 1500 * 4
    assert servo_data(conn, 3, 60 * SEC) == 1500 * 4  # and stays there
    conn.receive(b"rr1-3--0--0-ss1", 60 * SEC)  # Normal Send 0 on a servo
    assert servo_data(conn, 3, 61 * SEC) == 1000 * 4
    conn.receive(b"rr1-3--2000--0-ss1", 61 * SEC)  # turn round half-way
    assert servo_data(conn, 3, 62 * SEC) == 1500 * 4
    assert servo_data(conn, 2, 62 * SEC) == 4000  # other servos did not move


def test_internal_script_sweeps_servos_and_stopping_returns_them():
    robot = make_robot(servo_speed=1000)
    conn = robot.connect(ServerMode.VPN)
    conn.receive(b"rr1-0--0--120-ss1", 0)
    assert robot.internal_script == 120
    positions = [servo_data(conn, 1, t * SEC // 4) // 4 for t in range(13)]
    # from 1000 up to 2000, down to 0, up again
    assert positions == [1000, 1250, 1500, 1750, 2000, 1750, 1500, 1250, 1000, 750, 500, 250, 0]
    conn.receive(b"rr1-0--0--23-ss1", 3 * SEC)  # another internal script: the sweep goes on
    assert servo_data(conn, 1, 3 * SEC + SEC // 4) // 4 == 250
    conn.receive(b"rr1-1--1800--0-ss1", 3 * SEC + SEC // 4)  # taken up after the script
    conn.receive(b"rr1-0--0--267-ss1", 3 * SEC + SEC // 4)
    assert robot.internal_script is None
    assert servo_data(conn, 1, 3 * SEC + SEC // 2) // 4 == 500
    assert servo_data(conn, 1, 10 * SEC) // 4 == 1800
    assert servo_data(conn, 0, 10 * SEC) // 4 == 1000


def test_external_scripts_change_state_only():
    robot = make_robot()
    conn = robot.connect(ServerMode.VPN)
    conn.receive(b"rr1-0--0--273-ss1", 0)
    assert robot.external_script == 273 and robot.internal_script is None
    assert servo_data(conn, 0, 5 * SEC) == 4000
    conn.receive(b"rr1-0--0--269-ss1", 6 * SEC)
    assert robot.external_script is None


def test_state_is_shared_by_every_connection():
    robot = make_robot()
    a, b = robot.connect(ServerMode.VPN), robot.connect(ServerMode.WINSOCK, PASSWORD)
    a.receive(b"rr1-7--1--0-ss1rr1-4--2000--0-ss1", 0)
    b.receive(PASSWORD, 0)
    assert robot.switches[7]
    assert servo_data(b, 4, 2 * SEC) == 8000


# -- sensors -------------------------------------------------------------------------------------


def test_sensor_values_stay_in_range_and_change_over_time():
    robot = make_robot()
    for ch in range(12, 24):
        values = [robot.sensor_value(ch, t * SEC // 10) for t in range(600)]
        assert all(0 <= v <= 1024 for v in values)
        assert len(set(values)) > 20, f"channel {ch} hardly moves"


def test_sensor_values_are_reproducible_per_seed():
    a, b, c = make_robot(seed=7), make_robot(seed=7), make_robot(seed=8)
    times = [t * 123_456_789 for t in range(100)]
    series = [[r.sensor_value(ch, t) for ch in range(24) for t in times] for r in (a, b, c)]
    assert series[0] == series[1]
    assert series[0] != series[2]


def test_every_shape_is_used_and_each_is_smooth():
    shapes = {type(make_signal(seed, ch)) for seed in range(3) for ch in range(24)}
    assert shapes == {Sine, Ramp, Noise} and len(SHAPES) == 3
    for ch in range(24):
        signal = make_signal(0, ch)
        steps = [abs(signal.value(t / 100 + 0.01) - signal.value(t / 100)) for t in range(2000)]
        if not isinstance(signal, Ramp):  # a sawtooth drops back once a period
            assert max(steps) < 60, type(signal).__name__


# -- Set Configuration ---------------------------------------------------------------------------


def set_config(entries: list[tuple[int, int, int]], checksum: int | None = None) -> bytes:
    message_entries = tuple(m.SetConfigEntry(*e) for e in entries)
    if checksum is None:
        checksum = sum(e[0] for e in entries) % 256
    return encode(m.SetConfiguration(message_entries, checksum))


def test_set_configuration_changes_the_listed_channels_and_sends_no_reply():
    robot = make_robot("servo:0-1,switch1:2,sensor:3")
    conn = robot.connect(ServerMode.VPN)
    out = conn.receive(set_config([(12, 1, 2), (12, 2, 1), (12, 4, 0)]), SEC)
    assert data(out) == []
    assert format_channels(robot.channels) == "servo:0,sensor:1,switch1:2,sensor:3,servo:4"
    assert data(conn.receive(b"rr1-24--0--0-ss1", SEC)) == [b"sr1-\x05000200101200000-ss1"]


@pytest.mark.parametrize("frame, rule", [
    (set_config([(12, 0, 2)], checksum=13), "PW-SETCFG-CHECKSUM"),
    (set_config([(12, 30, 2)]), "PW-SETCFG-PORT"),
    (set_config([(12, 0, 7)]), "PW-SETCFG-UNIT"),
    (set_config([(12, 6, 2)]), None),  # would leave channel 5 without a unit
])
def test_bad_set_configuration_is_ignored(frame, rule):
    robot = make_robot("servo:0-4")
    out = robot.connect(ServerMode.VPN).receive(frame, SEC)
    assert data(out) == []
    assert format_channels(robot.channels) == "servo:0-4"
    assert "ignored" in " ".join(n.text for n in out.notes)
    if rule:
        assert rule in rule_ids(out)


def test_set_configuration_may_extend_the_channel_map_without_gaps():
    robot = make_robot("servo:0-4")
    robot.connect(ServerMode.VPN).receive(set_config([(12, 5, 2), (12, 6, 1)]), SEC)
    assert format_channels(robot.channels) == "servo:0-4,sensor:5,switch:6"


def test_set_configuration_in_the_layout_lines_raw_byte_form_is_ignored():
    robot = make_robot("servo:0-1")
    frame = b"sr1-\x19" + bytes([12, 0, 2, 12]) + b"0-ss1"  # Data1 as the raw byte 25, one entry
    out = robot.connect(ServerMode.VPN).receive(frame, SEC)
    assert "PW-SETCFG-FORM" in rule_ids(out)
    assert format_channels(robot.channels) == "servo:0-1"


def test_checksum_rule_is_configurable():
    frame = set_config([(12, 0, 2), (12, 1, 2)], checksum=28)  # dev-unit-sum: 12+2 + 12+2
    default, other = make_robot("servo:0-1"), make_robot("servo:0-1", checksum_rule="dev-unit-sum")
    default.connect(ServerMode.VPN).receive(frame, 0)
    other.connect(ServerMode.VPN).receive(frame, 0)
    assert format_channels(default.channels) == "servo:0-1"
    assert format_channels(other.channels) == "sensor:0-1"


# -- camera -------------------------------------------------------------------------------------------


def test_camera_frames_count_up():
    robot = make_robot()
    conn = robot.connect(ServerMode.VPN)
    assert data(conn.receive(b"rr1-29--0--0-ss1" * 3, SEC)) == [fake_camera(n, 1.0) for n in (1, 2, 3)]


def test_camera_off_sends_nothing():
    robot = make_robot(camera=None)
    out = robot.connect(ServerMode.VPN).receive(b"rr1-29--0--0-ss1", SEC)
    assert data(out) == [] and "camera is off" in out.notes[0].text


def test_test_picture_is_a_small_jpeg_the_framer_reads_whole():
    pictures = [render_frame(n, n / 3) for n in (1, 2, 999_999)] + [fake_camera(1, 0.5)]
    for picture in pictures:
        assert picture.startswith(b"\xff\xd8\xff") and picture.endswith(b"\xff\xd9")
        assert len(picture) < 32 * 1024
        items = Framer().feed(picture, 0)
        assert [(i.kind, i.raw) for i in items] == [(ItemKind.IMAGE, picture)]
    assert len(set(pictures)) == 4


# -- conformance: the analyzer finds nothing wrong with the simulator -----------------------------------


def test_a_whole_session_is_conformant_to_the_analyzer():
    robot = make_robot(camera=render_frame)
    conn = robot.connect(ServerMode.WINSOCK, PASSWORD)
    session = Session()
    observations = []
    t = 0

    def both(client_bytes: bytes, out: Output | None = None) -> None:
        nonlocal t
        t += SEC // 10
        out = out or conn.receive(client_bytes, t)
        observations.extend(session.receive(Direction.C2S, client_bytes, t))
        for reply in out.replies:
            observations.extend(session.receive(Direction.S2C, reply.data, t))

    both(b"", conn.start(0))
    both(PASSWORD)
    both(b"rr1-24--0--0-ss1")
    for frame in (b"rr1-12--0--0-ss1", b"rr1-3--0--2-ss1", b"rr1-3--1200--0-ss1", b"rr1-7--1--0-ss1",
                  b"rr1-7--0--0-ss1", b"rr1-0--0--11-ss1", b"rr1-3--0--2-ss1", b"rr1-0--0--267-ss1",
                  b"rr1-0--0--271-ss1", b"rr1-0--0--269-ss1", b"rr1-29--0--0-ss1", SET_CONFIG_EXAMPLE):
        both(frame)
    observations.extend(session.close(t + SEC))
    assert session.handshake_outcome == "readytogo"
    assert dict(session.violation_counts) == {}
    answers = [o for o in observations if o.direction is Direction.S2C and o.item.kind in (
        ItemKind.RESPONSE, ItemKind.CONFIG, ItemKind.IMAGE)]
    assert [type(o.answers.message).__name__ for o in answers] == [
        "FetchConfiguration", "SensorRequest", "ServoPositionRequest", "ServoPositionRequest", "FetchCameraImage"]
