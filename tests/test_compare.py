"""Judging a replayed answer against the recorded one: modes, tolerances, rules, diffs."""

from __future__ import annotations

import pytest

from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.analysis.compare import (
    CompareError,
    CompareRules,
    ServoMotion,
    Status,
    answer_key,
    compare,
    headline,
    side_by_side,
)
from whiztap.analyzer.protocol.messages import (
    ChannelConfig,
    ChannelResponse,
    ConfigurationSettings,
    FetchConfiguration,
    NormalSend,
    PlayInternalScript,
    SensorRequest,
    ServoPositionRequest,
    StopInternalScript,
)
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.session import Session

CONFIG = ConfigurationSettings(tuple([ChannelConfig(0)] * 6 + [ChannelConfig(1)] * 6 + [ChannelConfig(2)] * 12))
EXACT, STRUCTURE, NONE = (CompareRules.parse(m) for m in ("exact", "structure", "none"))


def _observe(*steps: tuple[Direction, bytes]) -> list[Observation]:
    """A VPN session after Fetch Configuration; the observations of ``steps``."""
    session = Session()
    session.receive(Direction.C2S, encode(FetchConfiguration()), 1)
    session.receive(Direction.S2C, encode(CONFIG), 2)
    out = []
    for t, (direction, data) in enumerate(steps, start=3):
        out += [e for e in session.receive(direction, data, t) if isinstance(e, Observation)]
    return out


def answer(request, response) -> Observation:
    return _observe((Direction.C2S, encode(request)), (Direction.S2C, encode(response)))[-1]


def sensor(value: int, channel: int = 12) -> Observation:
    return answer(SensorRequest(channel), ChannelResponse(channel, value))


def servo(data: int, channel: int = 2) -> Observation:
    return answer(ServoPositionRequest(channel), ChannelResponse(channel, data))


def test_exact_wants_identical_bytes():
    assert compare(sensor(431), sensor(431), EXACT).status is Status.MATCH
    verdict = compare(sensor(431), sensor(388), EXACT)
    assert verdict.status is Status.MISMATCH and not verdict.match
    assert [(d.field, d.recorded, d.replayed) for d in verdict.differences] == [("sensor_value", 431, 388)]


def test_structure_checks_sensor_readings_only_for_their_range():
    assert compare(sensor(431), sensor(17), STRUCTURE).match
    verdict = compare(sensor(431), sensor(1500), STRUCTURE)  # above the 1024 a sensor can read
    assert verdict.status is Status.MISMATCH
    assert "out of range 0-1024" in verdict.differences[0].note


def test_structure_wants_the_same_channel_and_kind():
    verdict = compare(sensor(431, 12), sensor(431, 13), STRUCTURE)
    assert [d.field for d in verdict.differences] == ["channel"]
    mixed = compare(sensor(431), servo(4000), STRUCTURE)
    assert {"channel", "sensor_value", "servo_position"} <= {d.field for d in mixed.differences}


def test_a_tolerance_replaces_the_range_check():
    rules = CompareRules.parse("structure", ["sensor_value=20"])
    assert compare(sensor(431), sensor(450), rules).match
    verdict = compare(sensor(431), sensor(452), rules)
    assert verdict.differences[0].note == "differs by 21, tolerance 20"
    assert compare(sensor(431), sensor(452), CompareRules.parse("exact", ["sensor_value=25"])).match


def test_a_servo_at_rest_must_read_the_same_and_one_in_motion_only_in_range():
    assert compare(servo(4000), servo(4400), STRUCTURE, at_rest=False).match
    verdict = compare(servo(4000), servo(4400), STRUCTURE, at_rest=True)
    assert verdict.differences[0].field == "servo_position"
    assert verdict.differences[0].note == "servo at rest in the recording"


def test_servo_motion_knows_a_servo_at_its_commanded_position():
    motion = ServoMotion()
    reading = servo(6000)  # position 1500
    assert not motion.at_rest(reading)  # no target known
    [send] = _observe((Direction.C2S, encode(NormalSend(2, 1500))))
    motion.observe(send)
    assert motion.at_rest(reading)
    assert not motion.at_rest(servo(5000))  # still on its way
    motion.observe(_observe((Direction.C2S, encode(PlayInternalScript(20))))[0])
    assert not motion.at_rest(reading)  # a script sweeps every servo
    motion.observe(_observe((Direction.C2S, encode(StopInternalScript())))[0])
    assert motion.at_rest(reading)
    assert not motion.at_rest(sensor(6))


def test_ignored_fields_and_kinds():
    rules = CompareRules.parse("exact", ignore_fields=["sensor_value"])
    assert compare(sensor(431), sensor(1), rules).match
    assert not compare(sensor(431, 12), sensor(431, 13), rules).match
    by_meaning = CompareRules.parse("exact", ignore_kinds=["sensor"])
    assert compare(sensor(431), sensor(1), by_meaning).status is Status.IGNORED
    assert not compare(servo(1), servo(2), by_meaning).match
    assert compare(sensor(1), None, CompareRules.parse("exact", ignore_kinds=["response"])).status is Status.IGNORED


def test_missing_extra_unanswered_and_none():
    assert compare(sensor(431), None, STRUCTURE).status is Status.MISSING
    assert compare(None, sensor(431), STRUCTURE).status is Status.EXTRA
    assert compare(None, None, STRUCTURE).status is Status.UNANSWERED
    assert compare(None, None, STRUCTURE).match
    assert compare(sensor(431), sensor(2), NONE).status is Status.IGNORED
    assert compare(sensor(431), None, NONE).match


def test_configuration_differences_name_the_channel_map():
    recorded = answer(FetchConfiguration(), CONFIG)
    other = answer(FetchConfiguration(), ConfigurationSettings(CONFIG.channels[:6] + (ChannelConfig(1, 0, 1),) * 18))
    verdict = compare(recorded, other, STRUCTURE)
    diffs = {d.field: d for d in verdict.differences}
    assert diffs["units"].recorded == "0-5 servo, 6-11 switch0, 12-23 sensor"
    assert diffs["units"].replayed == "0-5 servo, 6-23 switch1"
    assert "channels" not in diffs  # both have 24


def test_side_by_side_shows_both_answers_and_each_difference():
    recorded, replayed = sensor(431), sensor(388)
    verdict = compare(recorded, replayed, EXACT)
    lines = side_by_side(recorded, replayed, verdict)
    assert lines[0].split() == ["recorded", "|", "replayed"]
    assert "cr1-12--431--0-ss1" in lines[1] and "cr1-12--388--0-ss1" in lines[1]
    assert "Sensor value ch 12 = 431" in lines[2] and "Sensor value ch 12 = 388" in lines[2]
    assert lines[3].split("|")[0].strip() == "sensor_value: 431"
    assert lines[3].split("|")[1].strip() == "sensor_value: 388"
    missing = side_by_side(recorded, None, compare(recorded, None, EXACT))
    assert "(no answer)" in missing[1]
    request = _observe((Direction.C2S, encode(SensorRequest(12))))[0]
    assert headline(verdict, 1, 0.25, request) == \
        "MISMATCH c1 at 0.250000 s after rr1-12--0--0-ss1 (Sensor Request ch 12)"


def test_answer_keys():
    [request] = _observe((Direction.C2S, encode(SensorRequest(12))))
    assert answer_key(request) == (("Sensor Request", 12), True)
    [send] = _observe((Direction.C2S, encode(NormalSend(2, 10))))
    assert answer_key(send) is None
    ambiguous = [e for e in Session().receive(Direction.C2S, b"rr1-24--0--0-ss1rr1-12--0--0-ss1", 1)
                 if isinstance(e, Observation)][1]  # no channel map yet
    assert ambiguous.message is None
    assert answer_key(ambiguous) == (("Sensor Request", 12), False)


@pytest.mark.parametrize("args, message", [
    (("fuzzy",), "unknown compare mode 'fuzzy'"),
    (("structure", ["sensor=3"]), "--tolerance: unknown field 'sensor'"),
    (("structure", ["sensor_value"]), "--tolerance wants FIELD=N"),
    (("structure", ["sensor_value=-1"]), "--tolerance wants FIELD=N"),
    (("structure", (), ["colour"]), "--ignore-field: unknown field 'colour'"),
    (("structure", (), (), ["video"]), "--ignore-kind: unknown kind 'video'"),
])
def test_bad_rules_are_one_line_errors(args, message):
    with pytest.raises(CompareError) as e:
        CompareRules.parse(*args)
    assert str(e.value).startswith(message) and "\n" not in str(e.value)
