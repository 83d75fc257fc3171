"""The planted server bugs (``whiztap sim --bug``): each one seen on the wire by
a raw client over a real socket, judged by the analyzer's Session where it
breaks a rule, and the same script against the clean simulator unaffected."""

from __future__ import annotations

import asyncio
import json
import re
from pathlib import Path

import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import decode, encode
from whiztap.analyzer.protocol.framing import Framer, Item, ItemKind
from whiztap.analyzer.protocol.observations import Direction, LateViolation
from whiztap.analyzer.protocol.session import Session
from whiztap.sniffer.sim.bugs import BUGS, BugError, Planted, SplitCrash, table
from whiztap.sniffer.sim.robot import Robot, ServerMode
from whiztap.sniffer.sim.channels import DEFAULT_CHANNELS, parse_channels
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import run_cli, start_process
from tests.record_support import recording
from tests.replay_support import until_closed

C, S = Direction.C2S, Direction.S2C
FROZEN = 42_000_000_000  # a stopped clock: the same sensor values every run
CONFIG = encode(m.FetchConfiguration())
CAMERA = encode(m.FetchCameraImage())
PASSWORD = b"progwhiz"
CRASHING = {"split-crash", "crash-on-frame"}
DOCS = Path(__file__).resolve().parent.parent / "docs" / "simulator.md"


def sensor(channel: int) -> bytes:
    return encode(m.SensorRequest(channel))


def servo(channel: int) -> bytes:
    return encode(m.ServoPositionRequest(channel))


class Wire:
    """A raw client: bytes out exactly as given, bytes in as they came, and
    the transcript in the order this client saw it, for the analyzer."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer
        self.transcript: list[tuple[Direction, bytes]] = []
        self.received = b""

    @classmethod
    async def open(cls, sim: Simulator | int) -> Wire:
        """A connection to the simulator, or to a port (a proxy in front of one)."""
        port = sim if isinstance(sim, int) else sim.port
        return cls(*await asyncio.open_connection("127.0.0.1", port))

    async def send(self, data: bytes) -> None:
        self.transcript.append((C, data))
        self.writer.write(data)
        await self.writer.drain()

    async def read_until(self, ends: bytes) -> bytes:
        """Read at least once, until what came so far ends with ``ends``; what came."""
        async with asyncio.timeout(10):
            self._got(await self.reader.read(65536) or self._closed())
            while not self.received.endswith(ends):
                self._got(await self.reader.read(65536) or self._closed())
        return self.received

    async def finish(self) -> bytes:
        """Half-close and read to the end: every reply the server had for us
        (it closes once it has served our last byte), with no wait guessed."""
        self.writer.write_eof()
        async with asyncio.timeout(10):
            while data := await self.reader.read(65536):
                self._got(data)
        self.writer.close()
        return self.received

    def _got(self, data: bytes) -> None:
        self.transcript.append((S, data))
        self.received += data

    def _closed(self) -> bytes:
        raise AssertionError(f"the server closed after {self.received!r}")

    def items(self) -> list[Item]:
        framer = Framer()
        return framer.feed(self.received, 0) + framer.end(0)

    def violations(self) -> list[tuple[str, str]]:
        """Every (rule, detail) the analyzer's Session finds in the transcript."""
        session = Session()
        events = []
        for t, (direction, data) in enumerate(self.transcript, start=1):
            events += session.receive(direction, data, t)
        events += session.close(len(self.transcript) + 1)
        found = []
        for e in events:
            found += [e.violation] if isinstance(e, LateViolation) else e.violations
        return [(v.rule_id, v.detail) for v in found]

    def rules(self) -> set[str]:
        return {rule for rule, _ in self.violations()}


def responses(wire: Wire) -> list[m.ChannelResponse]:
    return [decode(i.kind, i.raw).message for i in wire.items() if i.kind is ItemKind.RESPONSE]


async def played(bugs: tuple[str, ...], script, mode: str = "vpn") -> Wire:
    """A script played by a raw client against a simulator with ``bugs``."""
    async with Simulator(mode=mode, clock=lambda: FROZEN, bugs=bugs) as sim:
        wire = await Wire.open(sim)
        await script(wire)
        assert not sim.crashed.is_set() and sim.stats.errors == 0
        return wire


async def both(bug: str, script, mode: str = "vpn") -> tuple[Wire, Wire]:
    """The same script against the clean simulator and one with ``bug`` planted."""
    return await played((), script, mode), await played((bug,), script, mode)


async def configured(wire: Wire, *requests: bytes) -> bytes:
    """Fetch the configuration first (VPN's rule), then send the requests in
    one write and read every reply to the end."""
    await wire.send(CONFIG)
    await wire.read_until(b"-ss1")
    await wire.send(b"".join(requests))
    return await wire.finish()


# -- each bug on the wire ----------------------------------------------------------------------------


async def test_out_of_range_sends_sensor_values_past_1024_and_the_analyzer_names_it():
    clean, buggy = await both("out-of-range", lambda w: configured(w, sensor(12), servo(0)))
    assert responses(clean)[0].data <= 1024
    assert responses(buggy)[0].data == responses(clean)[0].data + 1025
    assert responses(buggy)[1] == responses(clean)[1]  # a servo's data is left alone
    assert clean.rules() == set() and buggy.rules() == {"PW-RANGE-SENSOR"}


async def test_wrong_channel_answers_name_the_next_channel():
    clean, buggy = await both("wrong-channel", lambda w: configured(w, sensor(12), servo(0), sensor(23)))
    assert [r.channel for r in responses(clean)] == [12, 0, 23]
    assert [r.channel for r in responses(buggy)] == [13, 1, 0]
    assert clean.rules() == set()
    assert {"PW-PAIR-UNSOLICITED", "PW-PAIR-UNANSWERED"} <= buggy.rules()


async def fetch(wire: Wire) -> None:
    await wire.send(CONFIG)
    await wire.finish()


async def blind_password(wire: Wire) -> None:
    """The password sent unasked: the only way to the no-sendchkpass bug's readytogo."""
    await wire.send(PASSWORD)
    await wire.read_until(b"readytogo")
    await wire.send(CONFIG)
    await wire.finish()


async def test_bad_config_answers_with_a_non_digit_unit_type():
    clean, buggy = await both("bad-config", fetch)
    assert [i.kind for i in buggy.items()] == [ItemKind.CONFIG]
    assert buggy.received.replace(b"?", b"2") == clean.received and buggy.received.endswith(b"?00-ss1")
    assert clean.rules() == set() and buggy.rules() == {"PW-CFG-DIGIT"}


async def test_out_of_order_swaps_pipelined_answers_in_pairs():
    clean, buggy = await both("out-of-order", lambda w: configured(w, *map(sensor, (12, 13, 14, 15, 16))))
    assert [r.channel for r in responses(clean)] == [12, 13, 14, 15, 16]
    assert [r.channel for r in responses(buggy)] == [13, 12, 15, 14, 16]  # the odd one stays


async def test_drop_nth_leaves_every_fifth_answered_request_unanswered():
    # the configuration is the first answered request: the 5th is channel 15's
    clean, buggy = await both("drop-nth", lambda w: configured(w, *map(sensor, range(12, 22))))
    assert [r.channel for r in responses(clean)] == list(range(12, 22))
    assert [r.channel for r in responses(buggy)] == [12, 13, 14, 16, 17, 18, 19, 21]
    assert clean.rules() == set() and buggy.rules() == {"PW-PAIR-UNANSWERED"}


async def test_bad_trailer_spoils_every_seventh_framed_answer():
    clean, buggy = await both("bad-trailer", lambda w: configured(w, *map(sensor, range(12, 20))))
    texts = re.findall(rb"cr1-\d+--\d+--0-ss\d", buggy.received)
    assert [t.endswith(b"ss2") for t in texts] == [False] * 5 + [True] + [False] * 2  # 7th of config + 8
    assert buggy.received.replace(b"-ss2", b"-ss1") == clean.received
    assert clean.rules() == set() and "PW-FRAME-TRUNCATED" in buggy.rules()


async def test_camera_length_makes_the_image_unframeable():
    clean, buggy = await both("camera-length", lambda w: configured(w, CAMERA))
    assert [i.kind for i in clean.items()] == [ItemKind.CONFIG, ItemKind.IMAGE]
    image = clean.items()[1].raw
    assert int.from_bytes(buggy.received[-len(image) + 4:][:2], "big") == int.from_bytes(image[4:6], "big") + 1
    assert ItemKind.IMAGE not in [i.kind for i in buggy.items()]
    assert clean.rules() == set() and "PW-FRAME-GARBAGE" in buggy.rules()


async def test_silent_after_garbage_never_answers_again():
    clean, buggy = await both("silent-after-garbage", lambda w: configured(w, b"#", sensor(12), sensor(13)))
    assert [r.channel for r in responses(clean)] == [12, 13]
    assert responses(buggy) == []
    assert clean.rules() == {"PW-FRAME-GARBAGE"}
    assert buggy.rules() == {"PW-FRAME-GARBAGE", "PW-PAIR-UNANSWERED"}


async def test_any_password_is_accepted():
    async def wrong_password(wire: Wire) -> None:
        await wire.read_until(b"sendchkpass")
        await wire.send(b"wrongpwd")  # as long as the real one
        await wire.finish()

    clean, buggy = await both("any-password", wrong_password, mode="winsock")
    assert clean.received == b"sendchkpassFailed Validation"
    assert buggy.received == b"sendchkpassreadytogo"


async def test_no_sendchkpass_answers_readytogo_unasked():
    async def password_when_asked(wire: Wire) -> None:
        await wire.read_until(b"sendchkpass")
        await blind_password(wire)

    clean = await played((), password_when_asked, mode="winsock")
    buggy = await played(("no-sendchkpass",), blind_password, mode="winsock")
    assert clean.received.startswith(b"sendchkpassreadytogosr1-")
    assert buggy.received.startswith(b"readytogosr1-")
    assert clean.rules() == set()
    assert ("PW-HS-ORDER", "got 'readytogo' from the server, expected 'sendchkpass' from the server or a first "
            "command from the client") in buggy.violations()


# -- one verdict: the analyzer on a recording through the proxy --------------------------------------------


RULE_SCRIPTS = {  # a script showing each bug that breaks a rule of the analyzer
    "out-of-range": ("vpn", lambda w: configured(w, sensor(12), servo(0))),
    "wrong-channel": ("vpn", lambda w: configured(w, sensor(12))),
    "bad-config": ("vpn", fetch),
    "drop-nth": ("vpn", lambda w: configured(w, *map(sensor, range(12, 22)))),
    "bad-trailer": ("vpn", lambda w: configured(w, *map(sensor, range(12, 20)))),
    "camera-length": ("vpn", lambda w: configured(w, CAMERA)),
    "silent-after-garbage": ("vpn", lambda w: configured(w, b"#", sensor(12))),
    "no-sendchkpass": ("winsock", blind_password),
}


def test_every_bug_that_breaks_a_rule_has_a_script():
    assert set(RULE_SCRIPTS) == {name for name, bug in BUGS.items() if bug.caught_by.startswith("PW-")}


@pytest.mark.parametrize("bug", sorted(RULE_SCRIPTS))
async def test_analyze_of_a_recording_names_the_rule_the_bug_breaks(bug, tmp_path):
    """Recorded through the proxy, ``whiztap analyze`` finds the rule the
    registry names, and exactly the rules the Session found on the client's
    own view of the same connection."""
    mode, script = RULE_SCRIPTS[bug]
    path = tmp_path / f"{bug}.mcap"
    async with Simulator(mode=mode, clock=lambda: FROZEN, bugs=(bug,)) as sim, \
            recording(sim.port, path) as rec:
        wire = await Wire.open(rec.proxy.port)
        await script(wire)
        await until_closed(sim)
        await rec.stop()
    result = run_cli("analyze", path, "--format", "json")
    assert result.returncode == 1, result.stderr
    [connection] = json.loads(result.stdout)["connections"]
    assert BUGS[bug].caught_by in connection["violations"]
    assert set(connection["violations"]) == wire.rules()


# -- the crashes --------------------------------------------------------------------------------------


async def until_read(sim: Simulator, count: int) -> None:
    """Until the simulator has read ``count`` bytes in all: its read came."""
    async with asyncio.timeout(10):
        while sim.stats.bytes_in < count:
            await asyncio.sleep(0.001)


async def assert_crashed(sim: Simulator, bystander: Wire, bug: str) -> None:
    """Crashed as a process would: every connection gone, nothing listening."""
    async with asyncio.timeout(10):
        await sim.crashed.wait()
    assert sim.crash_reason == bug
    try:
        async with asyncio.timeout(10):
            assert await bystander.reader.read() == b""
    except ConnectionResetError:
        pass
    with pytest.raises(ConnectionRefusedError):
        await asyncio.open_connection("127.0.0.1", sim.port)


async def test_crash_on_frame_brings_the_whole_server_down():
    async with Simulator(mode="vpn", bugs=("crash-on-frame",)) as sim:
        bystander, wire = await Wire.open(sim), await Wire.open(sim)
        await configured_alive(wire, encode(m.NormalSend(0, 0)).replace(b"--0--", b"--000--", 1))
        await wire.send(b"rr1-12--000--0-ss1")
        await assert_crashed(sim, bystander, "crash-on-frame")


async def configured_alive(wire: Wire, *requests: bytes) -> None:
    """Requests that must not crash the server: a sensor request after them is answered."""
    await wire.send(CONFIG)
    await wire.read_until(b"-ss1")
    await wire.send(b"".join(requests) + sensor(12))
    await wire.read_until(b"--0-ss1")
    assert wire.received.count(b"cr1-12--") == 1


async def test_the_clean_server_serves_the_crashing_frame():
    clean = await played((), lambda w: configured(w, b"rr1-12--000--0-ss1"))
    assert [r.channel for r in responses(clean)] == [12]
    assert clean.rules() == {"PW-SYNTAX-LEADING-ZERO"}


async def test_split_crash_dies_on_a_frame_split_across_reads():
    async with Simulator(mode="vpn", bugs=("split-crash",)) as sim:
        bystander, wire = await Wire.open(sim), await Wire.open(sim)
        await configured_alive(wire, sensor(13) + sensor(14))  # whole frames in one read: no crash
        await wire.send(b"rr1-12")
        await until_read(sim, len(CONFIG) + 3 * len(sensor(12)) + 6)
        await assert_crashed(sim, bystander, "split-crash")


async def test_the_clean_server_takes_a_frame_split_across_reads():
    async with Simulator(mode="vpn") as sim:
        wire = await Wire.open(sim)
        await wire.send(CONFIG)
        await wire.read_until(b"-ss1")
        await wire.send(b"rr1-12")
        await until_read(sim, len(CONFIG) + 6)
        await wire.send(b"--0--0-ss1")
        await wire.read_until(b"-ss1")
        assert not sim.crashed.is_set() and responses(wire)[0].channel == 12


# -- sans-IO properties -----------------------------------------------------------------------------


def planted(*names: str, mode: ServerMode = ServerMode.VPN):
    robot = Robot(parse_channels(DEFAULT_CHANNELS))
    return robot.connect(mode, PASSWORD if mode is ServerMode.WINSOCK else b"", hooks=Planted(names, robot))


@settings(max_examples=150, deadline=None)
@given(chunks=st.lists(st.binary(max_size=40) | st.sampled_from(
    [sensor(12), CONFIG, CAMERA, b"rr1-12--000--0-ss1", b"rr1-", b"-ss1", b"#", b"\r\n"]), max_size=30),
       mode=st.sampled_from(ServerMode))
def test_any_bytes_in_any_chunks_never_break_a_planted_server(chunks, mode):
    """Whatever a client sends, the bugs misbehave only as planted: no
    exception, a crash only from a crashing bug, and split-crash's copy of the
    held bytes never larger than what the framer holds."""
    names = tuple(name for name, bug in BUGS.items() if bug.needs in (None, mode))
    connection = planted(*names, mode=mode)
    connection.start(0)
    for t, chunk in enumerate(chunks, start=1):
        out = connection.receive(chunk, t)
        assert out.crash is None or out.crash in CRASHING
        if out.crash:
            return
        split = next(b for b in connection.hooks.bugs if isinstance(b, SplitCrash))
        assert len(split._held) <= connection._framer.buffered
    connection.end(len(chunks) + 1)


@settings(max_examples=100, deadline=None)
@given(frames=st.lists(st.sampled_from([sensor(12), servo(0), CONFIG, encode(m.NormalSend(1, 2000))]),
                       min_size=1, max_size=8), data=st.data())
def test_split_crash_crashes_exactly_when_a_read_ends_inside_a_frame(frames, data):
    stream = b"".join(frames)
    ends = {sum(map(len, frames[:i + 1])) for i in range(len(frames))}
    cuts = sorted(data.draw(st.sets(st.integers(1, len(stream) - 1), max_size=6)))
    connection = planted("split-crash")
    crashed = False
    for start, end in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        crashed = connection.receive(stream[start:end], 0).crash == "split-crash"
        if crashed:
            break
    assert crashed == any(cut not in ends for cut in cuts)


@settings(max_examples=200, deadline=None)
@given(fields=st.tuples(*[st.text("0123456789", min_size=1, max_size=5)] * 3))
@example(("12", "000", "0")).via("the planted frame")
@example(("012", "000", "0")).via("its channel with a leading zero")
@example(("0", "000", "0")).via("a servo's Normal Send 0")
@example(("12", "00", "0")).via("two digits")
def test_crash_on_frame_crashes_only_on_a_sensor_request_with_a_3_digit_value(fields):
    channel, value, code = fields
    frame = b"rr1-%s--%s--%s-ss1" % tuple(f.encode() for f in fields)
    out = planted("crash-on-frame").receive(frame, 0)
    sensor_channel = int(channel) <= 23 and parse_channels(DEFAULT_CHANNELS)[int(channel)].unit_type == 2
    assert (out.crash == "crash-on-frame") == (sensor_channel and value == "000" and code == "0")


# -- choosing bugs ----------------------------------------------------------------------------------------


def test_unknown_and_misplaced_bugs_are_refused():
    with pytest.raises(BugError, match="no planted bug 'nope'; known: out-of-range, "):
        Simulator(bugs=("nope",))
    for name in ("any-password", "no-sendchkpass"):
        with pytest.raises(BugError, match=f"{name} needs --mode winsock"):
            Simulator(mode="vpn", bugs=(name,))
    assert Simulator(bugs=("drop-nth", "drop-nth", "out-of-range")).bugs == ("drop-nth", "out-of-range")


def test_a_clean_simulator_has_no_hooks():
    sim = Simulator()
    assert sim.bugs == () and not sim.crashed.is_set()
    assert sim.robot.connect(ServerMode.VPN).hooks is None


def test_sim_bugs_lists_every_bug_and_exits_0():
    result = run_cli("sim", "--bugs")
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert [line.split()[0] for line in lines] == list(BUGS) and len(BUGS) == 12
    for line, bug in zip(lines, BUGS.values(), strict=True):
        assert line.endswith(bug.summary)


@pytest.mark.parametrize(("args", "text"), [
    (("--bug", "nope"), "whiztap: --bug: no planted bug 'nope'; known: out-of-range, wrong-channel, "),
    (("--bug", "drop-nth", "--bug", "any-password", "--mode", "vpn"),
     "whiztap: --bug: planted bug any-password needs --mode winsock (the server is in vpn mode)"),
    (("--mode", "vpn", "--bug", "no-sendchkpass"), "needs --mode winsock"),
])
def test_bad_bugs_are_one_line_and_exit_2(args, text):
    result = run_cli("sim", "--port", "0", *args)
    assert result.returncode == 2 and result.stderr.count("\n") == 1 and text in result.stderr, result


async def test_sim_process_exits_70_with_one_line_when_a_bug_crashes_it():
    proc = await start_process("sim", "--port", "0", "--mode", "vpn", "--bug", "crash-on-frame", "-q")
    line = (await asyncio.wait_for(proc.stdout.readline(), 60)).decode()
    port = int(re.search(r"127\.0\.0\.1:(\d+)", line)[1])
    assert line.endswith("(vpn, 24 channels, seed 0, planted bugs: crash-on-frame)\n")
    _, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"rr1-12--000--0-ss1")
    await writer.drain()
    _, err = await asyncio.wait_for(proc.communicate(), 60)
    assert proc.returncode == 70
    assert err.decode() == "whiztap sim: crashed (planted bug crash-on-frame)\n"
    writer.close()


def test_the_docs_table_is_the_registrys():
    assert table() in DOCS.read_text(), "docs/simulator.md's Planted bugs table differs from bugs.table()"
