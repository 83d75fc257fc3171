"""Scripts (sniffer/mitm/scripts.py) through the real proxy in front of the
simulator: the samples in samples/scripts/ do what their docstrings say, a
hook that raises is isolated (reported once, the frame untouched, the proxy
going on), a script that does not load stops ``whiztap record`` with one
line, and the hooks are called when they should be."""

from __future__ import annotations

import asyncio
import base64
import random
import runpy
import textwrap
from pathlib import Path

import pytest

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.sim.client import Client
from tests.cli_support import run_cli
from tests.record_support import LOCAL, WAIT
from tests.middle_support import (
    Middle,
    Raw,
    actions,
    answer_channel,
    delivered,
    held_ns,
    items_of,
    middle,
    sensor,
    sent,
)

SAMPLES = Path(__file__).resolve().parent.parent / "samples" / "scripts"
FLAKY = SAMPLES / "flaky_sensor.py"
LATE = SAMPLES / "late_servo.py"


def servo(ch: int) -> bytes:
    return encode(m.ServoPositionRequest(ch))


def script(tmp_path: Path, name: str, text: str) -> str:
    path = tmp_path / name
    path.write_text(textwrap.dedent(text))
    return str(path)


def causes(topics: dict[str, list[dict]]) -> set[str]:
    return {i["cause"] for i in topics.get("/interventions", [])}


# -- the samples --------------------------------------------------------------------------------------


async def _seen(mid: Middle, direction: Direction, count: int, conn: int = 1) -> None:
    """Wait until the proxy has decided ``count`` frames of ``direction``."""
    core, _ = mid.rec.controller.cores[conn]
    lane = core.lanes[direction]
    async with asyncio.timeout(WAIT):
        while lane.index < count:
            await asyncio.sleep(0.01)


async def test_flaky_sensor_drops_or_spoils_channel_12_answers_as_its_seed_says(tmp_path):
    sample = runpy.run_path(str(FLAKY))
    async with middle(tmp_path / "r.mcap", scripts=(str(FLAKY),)) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(*(sensor(12 + i % 2) for i in range(40)))  # channels 12 and 13 in turn
        await _seen(mid, Direction.S2C, 40)
        answers = await raw.until_quiet()
        await raw.close()
    topics = mid.topics()
    draws = random.Random(f"{sample['SEED']}:1")
    out = f"cr1-12--{sample['OUT_OF_RANGE']}--0-ss1".encode()
    expected = []
    for answer in items_of(sent(topics, "s2c")):  # as the robot answered, in order
        draw = draws.random() if answer_channel(answer) == 12 else 1.0
        if draw >= sample["DROP"]:
            expected.append(out if draw < sample["DROP"] + sample["OUT"] else answer)
    assert answers == expected
    assert [answer_channel(a) for a in answers].count(13) == 20  # channel 13 untouched
    assert {"drop", "replace"} == set(actions(topics)) and causes(topics) == {"script flaky_sensor.py"}
    assert mid.warnings == []


async def test_late_servo_delays_the_answers_to_servo_position_requests(tmp_path):
    async with middle(tmp_path / "r.mcap", scripts=(str(LATE),)) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(12))
        await raw.take(1)
        await raw.send(servo(0), sensor(13), servo(3))  # the sensor answer waits behind the late one
        answers = await raw.nothing_more(4)
        await raw.close()
        async with await Client.connect(LOCAL, mid.port) as client:
            await client.servo_position(2)
    assert [answer_channel(a) for a in answers] == [12, 0, 13, 3]
    topics = mid.topics()
    late = topics["/interventions"]
    assert [(i["conn"], i["action"], i["detail"]) for i in late] == [(1, "delay", "delayed 300 ms")] * 2 + [
        (2, "delay", "delayed 300 ms")]
    assert [i["before"] for i in late[:2]] == [a.decode() for a in answers[1::2]]
    # as recorded (gaps in the file, not a wall-clock race): the servo answers were held 300 ms from
    # the read they came in, on both connections; the sensor answer behind the first went in the same
    # write or after it, never before; the first sensor answer was not held behind anything
    held = dict(enumerate(held_ns(topics, "s2c")))
    assert [text.encode() for text, _ in held.values()] == answers
    assert held[1][1] >= 300_000_000 and held[3][1] >= 300_000_000
    by_text = {f["text"]: f for f in topics["/frames"] if f["conn"] == 1}
    assert held[2][1] + by_text[held[2][0]]["t_end_ns"] >= held[1][1] + by_text[held[1][0]]["t_end_ns"]
    assert held[0][1] + by_text[held[0][0]]["t_end_ns"] < min(
        r["t_ns"] for r in topics["/tcp/reads"] if r["conn"] == 1 and r["dir"] == "c2s" and
        servo(0) in base64.b64decode(r["data"]))
    [(servo_answer, servo_held)] = [(t, ns) for t, ns in held_ns(topics, "s2c", conn=2) if t.startswith("cr1-2--")]
    assert servo_held >= 300_000_000, servo_answer
    assert causes(topics) == {"script late_servo.py"}


# -- a hook that raises ---------------------------------------------------------------------------------


async def test_a_hook_that_raises_is_reported_once_and_every_frame_passes(tmp_path):
    path = script(tmp_path, "boom.py", """
        seen = []

        def frame(flow):
            seen.append(flow.text)
            raise RuntimeError("boom on " + flow.text)
    """)
    async with middle(tmp_path / "r.mcap", scripts=(path,)) as mid:
        async with await Client.connect(LOCAL, mid.port) as client:
            for ch in (12, 13, 14):
                assert 0 <= await client.sensor(ch) <= 1024
            await client.fetch_configuration()
        module = mid.rec.controller.scripts[0].module
        assert len(module.seen) == 8  # called for every frame both ways, the later ones too
    [warning] = mid.warnings
    assert warning.startswith("boom.py: its 'frame' hook raised")
    assert "Traceback" in warning and "RuntimeError: boom on rr1-12--0--0-ss1" in warning
    topics = mid.topics()
    assert "/interventions" not in topics
    for direction in ("c2s", "s2c"):
        assert b"".join(delivered(topics, direction)) == sent(topics, direction)


async def test_a_hook_that_changes_the_frame_and_then_raises_leaves_it_untouched(tmp_path):
    path = script(tmp_path, "half.py", """
        def frame(flow):
            flow.replace(b"cr1-12--1--0-ss1")
            flow.delay(5)
            flow.inject("sensor 13")
            flow.inject(b"hello\\r\\n", "s2c")
            flow.drop()
            raise ValueError("changed my mind")
    """)
    async with middle(tmp_path / "r.mcap", scripts=(path,)) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(12), sensor(14))
        answers = await raw.nothing_more(2)
        await raw.close()
    assert [answer_channel(a) for a in answers] == [12, 14]
    assert len(mid.warnings) == 1 and "ValueError: changed my mind" in mid.warnings[0]
    topics = mid.topics()
    assert "/interventions" not in topics
    assert b"".join(delivered(topics, "c2s")) == sensor(12) + sensor(14)
    assert b"".join(delivered(topics, "s2c")) == sent(topics, "s2c")
    # the 5 s delay was undone too: as recorded, no frame either way was held anywhere near it (a
    # kept delay would put every write 5 s or more after its read in the file, whatever the load)
    assert all(ns < 5_000_000_000 for way in ("c2s", "s2c") for _, ns in held_ns(topics, way))


# -- injection ------------------------------------------------------------------------------------------


async def test_an_injection_goes_right_behind_its_frame(tmp_path):
    path = script(tmp_path, "inject.py", """
        def frame(flow):
            if flow.direction == "c2s" and flow.channel == 12:
                flow.inject("sensor 13")  # toward the server, right behind this request
                flow.inject(b"hello\\r\\n", "s2c")  # toward the client
    """)
    async with middle(tmp_path / "r.mcap", scripts=(path,)) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(12), sensor(14))  # one read: the injection still goes between them
        got = await raw.nothing_more(4)
        await raw.close()
    assert got[0] == b"hello" and [answer_channel(a) for a in got[1:]] == [12, 13, 14]
    topics = mid.topics()
    assert b"".join(delivered(topics, "c2s")) == sensor(12) + sensor(13) + sensor(14)
    assert [(i["dir"], i["action"], i["after"]) for i in topics["/interventions"]] == [
        ("c2s", "inject", "rr1-13--0--0-ss1"), ("s2c", "inject", "hello\\r\\n")]
    assert causes(topics) == {"script inject.py"}


# -- opened and closed -------------------------------------------------------------------------------------


async def test_opened_and_closed_are_called_for_each_connection(tmp_path):
    path = script(tmp_path, "hooks.py", """
        calls = []

        def opened(conn):
            calls.append(("opened", conn))

        def closed(conn):
            calls.append(("closed", conn))
    """)
    async with middle(tmp_path / "r.mcap", scripts=(path,)) as mid:
        module = mid.rec.controller.scripts[0].module
        for conn in (1, 2):
            async with await Client.connect(LOCAL, mid.port) as client:
                await client.sensor(12)
                assert module.calls[-1] == ("opened", conn)
            async with asyncio.timeout(WAIT):
                while module.calls[-1] != ("closed", conn):
                    await asyncio.sleep(0.01)
    assert module.calls == [("opened", 1), ("closed", 1), ("opened", 2), ("closed", 2)]
    assert mid.warnings == []


# -- a script that does not load ----------------------------------------------------------------------------


@pytest.mark.parametrize(("name", "text", "says"), [
    ("syntax.py", "def frame(flow:\n", "failed to load: SyntaxError"),
    ("raises.py", "raise ImportError('no such robot')\n", "failed to load: ImportError: no such robot"),
    ("nohooks.py", "x = 1\n", "defines none of the hooks frame, opened, closed"),
    ("missing.py", None, "no such file"),
])
def test_a_script_that_does_not_load_stops_record_with_one_line(tmp_path, name, text, says):
    path = tmp_path / name
    if text is not None:
        path.write_text(text)
    done = run_cli("record", "--listen", "127.0.0.1:0", "--upstream", "127.0.0.1:9", "-o", tmp_path / "r.mcap",
                   "--script", path)
    assert done.returncode == 2
    [line] = done.stderr.splitlines()
    assert name in line and says in line and "Traceback" not in done.stderr
    assert not (tmp_path / "r.mcap").exists()
