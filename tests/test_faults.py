"""Every fault of the SPEC grammar through real sockets: a client, the
recording proxy in the middle, the simulator (or a plain server where exact
bytes matter).  Each effect is checked where it lands (at the client, at the
server) and in the recording (/tcp/reads: what each side sent,
/tcp/delivered: what the proxy wrote, /interventions: why)."""

from __future__ import annotations

import asyncio
import base64
import contextlib
import dataclasses
import itertools
import logging
import struct
import time
from collections import Counter

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.mitm.spec import FaultSpec, parse_fault
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE, get_rule
from whiztap.analyzer.protocol.codec import checksum_offset, decode, encode
from whiztap.analyzer.protocol.framing import Framer
from whiztap.analyzer.protocol.observations import Direction, Observation
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.mitm import lane as lane_module
from whiztap.analyzer.mitm.lane import HIGH_WATER
from whiztap.sniffer.sim.client import Client
from tests.middle_support import (
    Background,
    Middle,
    Raw,
    Reads,
    actions,
    answer_channel,
    delivered,
    exchange,
    held_ns,
    items_of,
    middle,
    sensor,
    sent,
)
from tests.cli_support import run_cli
from tests.record_support import LOCAL, WAIT
from tests.spec_vectors import ALL_FRAMES
from tests.streams import chunked

READ = 256 << 10  # the most asyncio reads from a socket at once
STREAM_HIGH_WATER = 64 << 10  # asyncio's default: a stream's drain() waits while its buffer is over it


# -- delay ----------------------------------------------------------------------------------------------


@pytest.mark.slow
async def test_delay_holds_every_answer_back_and_keeps_their_order(tmp_path):
    async with middle(tmp_path / "r.mcap", "delay:200ms dir:s2c") as mid:
        raw = await Raw.open(mid.port)
        await raw.send(*(sensor(ch) for ch in range(12, 20)))  # pipelined: one write
        answers = await raw.nothing_more(8)
        await raw.close()
    assert [answer_channel(a) for a in answers] == list(range(12, 20))
    topics = mid.topics()
    assert actions(topics) == ["delay"] * 8
    assert [(i["dir"], i["before"], i["detail"]) for i in topics["/interventions"]] == [
        ("s2c", a.decode(), "delayed 200 ms") for a in answers]
    assert b"".join(delivered(topics, "s2c")) == sent(topics, "s2c")  # late, not changed
    assert b"".join(delivered(topics, "c2s")) == sent(topics, "c2s")
    # as recorded: every answer written at least 200 ms after the read it came in (a recorded gap,
    # not a wall-clock race: the proxy's clock must pass the hold before it writes); the requests
    # went on before any answer was even read
    held = held_ns(topics, "s2c")
    assert [text.encode() for text, _ in held] == answers and all(ns >= 200_000_000 for _, ns in held)
    assert max(d["t_ns"] for d in topics["/tcp/delivered"] if d["dir"] == "c2s") <= min(
        r["t_ns"] for r in topics["/tcp/reads"] if r["dir"] == "s2c")


# -- drop, dup, corrupt, replace ----------------------------------------------------------------------


@pytest.mark.slow
async def test_drop_every_second_answer_of_one_channel(tmp_path):
    async with middle(tmp_path / "r.mcap", "drop dir:s2c kind:response ch:12 every:2") as mid:
        raw = await Raw.open(mid.port)
        await raw.send(*(sensor(ch) for _ in range(4) for ch in (12, 13)))
        answers = await raw.nothing_more(6)
        await raw.close()
    assert [answer_channel(a) for a in answers] == [12, 13, 13, 12, 13, 13]
    topics = mid.topics()
    assert actions(topics) == ["drop", "drop"]
    assert all(i["after"] == "" and i["before"].startswith("cr1-12--") for i in topics["/interventions"])
    assert [answer_channel(a) for a in items_of(sent(topics, "s2c"))] == [12, 13] * 4  # the server answered all
    assert items_of(b"".join(delivered(topics, "s2c"))) == answers


async def test_dup_sends_the_first_command_twice_and_the_server_answers_twice(tmp_path):
    async with middle(tmp_path / "r.mcap", "dup dir:c2s kind:command nth:1") as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(12))
        await raw.take(2)
        await raw.send(sensor(13))
        answers = await raw.nothing_more(3)
        await raw.close()
        assert mid.server.stats.answers_sent == 3
    assert [answer_channel(a) for a in answers] == [12, 12, 13]
    topics = mid.topics()
    assert b"".join(delivered(topics, "c2s")) == sensor(12) * 2 + sensor(13)
    assert sent(topics, "c2s") == sensor(12) + sensor(13)
    [dup] = topics["/interventions"]
    assert (dup["action"], dup["before"], dup["after"], dup["detail"]) == (
        "dup", escape(sensor(12)), escape(sensor(12)), "delivered 2 times")


async def test_corrupt_changes_the_set_configuration_checksum_and_the_server_ignores_it(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="whiztap.sim")
    entries = (m.SetConfigEntry(1, 12, 0),)  # channel 12: a sensor, made a servo
    frame = encode(m.SetConfiguration(entries, get_rule(DEFAULT_CHECKSUM_RULE).compute(entries)))
    async with middle(tmp_path / "r.mcap", "corrupt dir:c2s kind:set_config") as mid:
        async with await Client.connect(LOCAL, mid.port) as client:
            await client.send_raw(frame)
            config = await client.fetch_configuration()
        assert config.channels[12].unit_type == 2  # still a sensor: the server ignored it
        assert "PW-SETCFG-CHECKSUM" in caplog.text
        async with await Client.connect(LOCAL, mid.server.port) as direct:
            await direct.send_raw(frame)  # the frame itself, past the proxy, is taken
            assert (await direct.fetch_configuration()).channels[12].unit_type == 0
    topics = mid.topics()
    got = b"".join(delivered(topics, "c2s"))
    assert got.endswith(encode(m.FetchConfiguration()))  # the request after it passes as it came
    changed = got[:len(frame)]
    assert len(changed) == len(frame)
    assert [i for i in range(len(frame)) if changed[i] != frame[i]] == [checksum_offset(frame)]
    [corrupt] = topics["/interventions"]
    assert (corrupt["action"], corrupt["kind"]) == ("corrupt", "set_config")
    assert (corrupt["before"], corrupt["after"]) == (escape(frame), escape(changed))


@pytest.mark.slow
async def test_replace_the_first_answer_of_channel_12(tmp_path):
    spec = 'replace:"cr1-12--999--0-ss1" dir:s2c kind:response ch:12 nth:1'
    async with middle(tmp_path / "r.mcap", spec) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(13), sensor(12), sensor(12))
        answers = await raw.nothing_more(3)
        await raw.close()
    assert answers[1] == b"cr1-12--999--0-ss1"
    topics = mid.topics()
    original = items_of(sent(topics, "s2c"))
    assert answers == [original[0], b"cr1-12--999--0-ss1", original[2]]
    [replace] = topics["/interventions"]
    assert (replace["action"], replace["before"], replace["after"]) == ("replace", escape(original[1]),
                                                                        "cr1-12--999--0-ss1")


# -- slice and bandwidth ------------------------------------------------------------------------------


async def _config_in_reads(mid: Middle) -> Reads:
    _, reads = await asyncio.get_running_loop().create_connection(Reads, LOCAL, mid.port)
    reads.transport.write(encode(m.FetchConfiguration()))
    await reads.until(81)  # the simulator's configuration answer
    reads.transport.close()
    return reads


@pytest.mark.slow
async def test_slice_1_delivers_an_answer_a_byte_at_a_time(tmp_path):
    async with middle(tmp_path / "r.mcap", "slice:1 dir:s2c") as mid:
        reads = await _config_in_reads(mid)
    topics = mid.topics()
    assert bytes(reads.data) == sent(topics, "s2c")
    assert [len(d) for d in delivered(topics, "s2c")] == [1] * 81
    assert max(reads.sizes) <= 2 and len(reads.sizes) >= 40  # the client's reads were small too
    assert actions(topics) == ["slice"]


async def test_slice_range_delivers_pieces_of_two_to_four_bytes(tmp_path):
    async with middle(tmp_path / "r.mcap", "slice:2-4 dir:s2c") as mid:
        reads = await _config_in_reads(mid)
    topics = mid.topics()
    sizes = [len(d) for d in delivered(topics, "s2c")]
    assert bytes(reads.data) == b"".join(delivered(topics, "s2c")) == sent(topics, "s2c")
    assert all(2 <= s <= 4 for s in sizes[:-1]) and 1 <= sizes[-1] <= 4
    assert set(sizes[:-1]) == {2, 3, 4}


@pytest.mark.slow
async def test_bandwidth_paces_a_configuration_answer(tmp_path):
    async with middle(tmp_path / "r.mcap", "bandwidth:2kB/s dir:s2c") as mid, \
            await Client.connect(LOCAL, mid.port) as client:
        config = await client.fetch_configuration()
    assert len(config.channels) > 0
    _assert_paced(mid.topics(), 2000)


def _assert_paced(topics: dict[str, list[dict]], rate: int) -> None:
    """The answers went unchanged in writes of ``rate / 100`` bytes, the
    recorded time from the first write to the last at least what ``rate``
    allows (the first write goes at once): recorded gaps, not a wall clock."""
    writes = [d for d in topics["/tcp/delivered"] if d["dir"] == "s2c"]
    size = len(sent(topics, "s2c"))
    assert b"".join(base64.b64decode(d["data"]) for d in writes) == sent(topics, "s2c")
    assert max(d["size"] for d in writes) <= rate // 100 and len(writes) >= size // (rate // 100)
    assert writes[-1]["t_ns"] - writes[0]["t_ns"] >= (size - rate // 100) * 1_000_000_000 // rate
    assert {(i["action"], i["detail"]) for i in topics["/interventions"]} == {
        ("bandwidth", f"in writes of {rate // 100} bytes, 10 ms apart")}


# -- blackhole, reset, close ----------------------------------------------------------------------------


def closed_events(topics: dict[str, list[dict]]) -> list[dict]:
    return [e for e in topics["/tcp/events"] if e["event"] == "closed"]


def test_after_takes_seconds_and_counts():
    assert parse_fault("blackhole dir:s2c after:2s").after_ns == 2_000_000_000
    assert parse_fault("reset after:3s").after_ns == 3_000_000_000
    assert parse_fault("close dir:c2s after:10").after_frames == 10


@pytest.mark.slow
async def test_reset_after_a_time_resets_both_sides(tmp_path, caplog):
    caplog.set_level(logging.INFO, logger="whiztap.sim")
    async with middle(tmp_path / "r.mcap", "reset after:0.3s") as mid:
        raw = await Raw.open(mid.port)
        await raw.send(sensor(12))
        await raw.take(1)
        try:
            async with asyncio.timeout(WAIT):
                while await raw.reader.read(65536):
                    pass
        except ConnectionResetError:
            pass
        else:
            raise AssertionError("the client got a normal close, not a reset")
        async with asyncio.timeout(WAIT):  # the simulator's side was reset too
            while "reset" not in caplog.text.lower():
                await asyncio.sleep(0.01)
        await raw.close()
    topics = mid.topics()
    assert actions(topics) == ["reset"]
    [closed] = closed_events(topics)
    assert (closed["by"], closed["detail"]) == ("proxy", "reset by a fault")
    # as recorded, the reset came after:0.3s from the opening (the timer runs on the event loop's
    # clock, the recording on the proxy's: a millisecond of slack between the two), after the answer
    [opened] = [e for e in topics["/tcp/events"] if e["event"] == "opened"]
    [reset] = topics["/interventions"]
    assert reset["t_ns"] - opened["t_ns"] >= 299_000_000
    assert reset["t_ns"] > max(d["t_ns"] for d in topics["/tcp/delivered"] if d["dir"] == "s2c")


@pytest.mark.slow
async def test_close_after_ten_client_frames(tmp_path):
    switch = encode(m.ActivateSwitch(6))  # no answer: nothing races the close
    async with middle(tmp_path / "r.mcap", "close dir:c2s after:10") as mid:
        raw = await Raw.open(mid.port)
        for _ in range(10):
            await raw.send(switch)
        async with asyncio.timeout(WAIT):
            assert await raw.reader.read() == b""  # a FIN, not a reset
        await raw.close()
    topics = mid.topics()
    assert b"".join(delivered(topics, "c2s")) == switch * 10  # the ten got through first
    assert actions(topics) == ["close"]
    [closed] = closed_events(topics)
    assert (closed["by"], closed["detail"]) == ("proxy", "closed by a fault")


# -- the options: nth, every, prob with a seed, after:N, for:, conn: ------------------------------------

# Timing, counting and aiming (jitter, bandwidth's pacing, blackhole, prob:, after:, for:, conn:)
# are tested on a fake clock against the middle's core: tests/test_middle_core.py.


# -- no fault crashes the proxy ---------------------------------------------------------------------------


@pytest.mark.slow
async def test_odd_frames_and_a_reset_under_a_delay_leave_the_proxy_serving(tmp_path):
    empty = dataclasses.replace(parse_fault("replace:x dir:s2c kind:response nth:1 conn:1"), replacement=b"")
    faults = (empty, "corrupt dir:c2s kind:unframed,eol conn:1", "slice:3 dir:c2s conn:1",
              "delay:300ms dir:s2c conn:1", "reset after:0.45s conn:1")
    async with middle(tmp_path / "r.mcap", *faults) as mid:
        raw = await Raw.open(mid.port)
        await raw.send(b"hello\n", sensor(12), b"\n", sensor(13))  # no digits; 1-byte items
        await raw.take(1)  # the first answer became nothing, the second comes late
        await raw.send(sensor(14))  # its answer waits in the delay when the reset comes
        with contextlib.suppress(ConnectionResetError):
            await raw.reader.read()
        async with await Client.connect(LOCAL, mid.port) as client:  # a new connection is served
            assert 0 <= await client.sensor(12) <= 1024
        await raw.close()
    assert mid.warnings == [] and mid.loop_errors == []
    topics = mid.topics()
    assert b"".join(delivered(topics, "c2s")) == b"hellp\x0b" + sensor(12) + b"\x0b" + sensor(13) + sensor(14)
    assert delivered(topics, "s2c") == items_of(sent(topics, "s2c"))[1:2]
    assert "reset" in actions(topics, conn=1) and actions(topics, conn=2) == []


# -- flow control under a delay -------------------------------------------------------------------------


@pytest.mark.slow
async def test_a_delay_under_a_client_that_keeps_sending_pauses_the_client(tmp_path):
    chunk = (sensor(12) + b"x" * 1006 + b"\r\n") * 64  # 64 KiB a write: requests and long junk lines
    async with middle(tmp_path / "r.mcap", "delay:250ms dir:c2s") as mid:
        reader, writer = await asyncio.open_connection(LOCAL, mid.port)
        written = 0

        async def keep_sending() -> None:
            nonlocal written
            while True:
                writer.write(chunk)
                await writer.drain()
                written += len(chunk)

        async def keep_reading() -> None:
            while await reader.read(1 << 20):
                pass

        tasks = [asyncio.create_task(keep_sending()), asyncio.create_task(keep_reading())]
        conn = mid.rec.proxy.connections[1]
        lane = conn.middle.core.lanes[Direction.C2S]
        queued, before = [], []
        start = time.monotonic()
        while time.monotonic() - start < 0.5:  # the delay, then as long again with the bytes flowing
            await asyncio.sleep(0.02)
            queued.append(lane.queued)
            if mid.server.stats.bytes_in == 0:  # nothing delivered yet
                before.append((conn.client.received, writer.transport.get_write_buffer_size(), written))
        for task in tasks:
            task.cancel()
        await asyncio.gather(*tasks, return_exceptions=True)
        writer.transport.abort()
    assert before and max(queued) <= HIGH_WATER + READ
    # while the delay holds everything, the proxy takes one read past its mark, and the client's
    # writes wait at drain (what it did write sits in the kernel's socket buffers, not in the proxy)
    assert all(received <= HIGH_WATER + READ for received, _, _ in before)
    assert before[-1][1] > STREAM_HIGH_WATER  # the client's transport is over its mark: drain waits
    assert conn.client.received > before[-1][0]  # and the proxy read on once the delayed bytes flowed


# -- bytes no fault chose pass untouched and in order (property) ------------------------------------------

_PIECE = st.one_of(
    st.sampled_from(ALL_FRAMES),
    st.sampled_from([b"\r\n", b"\n", b"\r", b"rr1-", b"-ss1", b"cr1-12--", b"sr1-25--"]),
    st.binary(max_size=30),
)
_STREAM = st.lists(_PIECE, max_size=30).map(b"".join)
# in the middle of the stream both ways: c2s frames about channel 2 dropped, those about channel 0
# doubled, every s2c frame delayed
_PROPERTY_FAULTS = ("drop dir:c2s ch:2", "dup dir:c2s ch:0", "delay:1ms dir:s2c")


def _as_delivered(data: bytes, specs: tuple[FaultSpec, ...]) -> tuple[bytes, dict[str, int]]:
    """What the receiver of c2s ``data`` gets when ``specs`` act on its frames
    (framing does not depend on chunking), and how often each action acted."""
    framer = Framer()
    out, counts = bytearray(), {"drop": 0, "dup": 0}
    for index, item in enumerate(framer.feed(data, 0) + framer.end(1)):
        d = decode(item.kind, item.raw, item.reason)
        observation = Observation(index, Direction.C2S, item, d.message, d.candidates, d.violations)
        copies = 1
        for spec in specs:
            if copies and spec.action in counts and spec.selects(1, observation):
                copies = 0 if spec.action == "drop" else copies + 1
                counts[spec.action] += 1
        out += item.raw * copies
    return bytes(out), counts


@pytest.mark.slow
def test_what_no_fault_chose_passes_untouched_and_in_order(tmp_path, monkeypatch):
    monkeypatch.setattr(lane_module, "STALL_NS", int(WAIT * 1e9))  # an unfinished item waits for more (or the FIN)
    bg = Background(tmp_path / "property.mcap", _PROPERTY_FAULTS)
    specs = tuple(parse_fault(f) for f in _PROPERTY_FAULTS)
    conns = itertools.count(1)
    acted: Counter[str] = Counter()
    try:
        bg.run(bg.start())

        @settings(max_examples=40, deadline=None, suppress_health_check=list(HealthCheck))
        @example(c2s=b"rr1-2--0--0-ss1\nxyzrr1-0--0--0-ss1rr1-24--0--0-ss1rr1-", s2c=b"cr1-2--100--0-ss1\r\n??",
                 c2s_cuts=[5, 20], s2c_cuts=[3])
        @given(c2s=_STREAM, s2c=_STREAM.filter(lambda b: b"sendchkpass" not in b),
               c2s_cuts=st.lists(st.integers(0, 1000), max_size=8),
               s2c_cuts=st.lists(st.integers(0, 1000), max_size=8))
        def one_connection(c2s: bytes, s2c: bytes, c2s_cuts: list[int], s2c_cuts: list[int]) -> None:
            conn = next(conns)
            tag = struct.pack(">Q", conn)
            bg.server.replies[tag] = chunked(s2c, s2c_cuts)
            assert exchange(bg.rec.proxy.port, tag, chunked(c2s, c2s_cuts)) == s2c  # delayed, exact
            expected, counts = _as_delivered(tag + c2s, specs)
            deadline = time.monotonic() + WAIT
            while tag not in bg.server.received and time.monotonic() < deadline:  # the client's FIN on its way
                time.sleep(0.001)
            assert bg.server.received[tag] == expected
            told = [i.action for i in bg.taps.by_conn[conn] if i.direction is Direction.C2S]
            assert (told.count("drop"), told.count("dup")) == (counts["drop"], counts["dup"])
            acted.update(told)

        one_connection()
        bg.run(bg.stop())
    finally:
        bg.close()
    assert acted["drop"] and acted["dup"]  # the examples did put the faults to work


# -- a SPEC with an unknown word --------------------------------------------------------------------------


def test_an_unknown_word_in_a_spec_is_one_line_naming_it(tmp_path):
    done = run_cli("record", "--listen", "127.0.0.1:0", "--upstream", "127.0.0.1:9", "-o", tmp_path / "r.mcap",
                   "--fault", "delay:200ms dri:s2c")
    assert done.returncode == 2
    assert len(done.stderr.splitlines()) == 1 and "dri:s2c" in done.stderr and "Traceback" not in done.stderr
    assert not (tmp_path / "r.mcap").exists()
