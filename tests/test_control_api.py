"""The control API (sniffer/mitm/http_api.py, control_server.py) and
``whiztap ctl`` against a real recording proxy in front of the simulator,
over its default Unix socket: faults added and removed while traffic flows,
frames held, edited, dropped and injected, and every way a request can be
wrong costing nothing but itself.  Who may send a request at all (TCP, its
token, Host, Origin) is tests/test_control_security.py's; how ctl finds and
recognises the API, tests/test_ctl.py's."""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from urllib.parse import urlsplit


from whiztap.analyzer.protocol.frame_text import frame_from_text
from whiztap.sniffer.mitm import control_server
from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.mitm.control_guard import MAX_BODY
from whiztap.sniffer.record.record_run import MiddleSettings, Recording
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import Ran, run_cli, start_process
from tests.record_support import LOCAL, WAIT, closed_port, read_all, recording

DROP_EVERY_SECOND = "drop dir:s2c kind:response ch:12 every:2"


# -- helpers -----------------------------------------------------------------------------------------


@contextlib.asynccontextmanager
async def proxied(path, control: Endpoint | None = None, **middle) -> AsyncIterator[tuple[Recording, Client]]:
    """The simulator behind a recording with the control API (by default on a
    new socket in the runtime folder, as a bare ``--control``), and a client through it."""
    settings = MiddleSettings(control=control or Endpoint(path=""), **middle)
    async with Simulator(port=0, mode="vpn", seed=7) as sim, recording(sim.port, str(path), middle=settings) as rec:
        client = await Client.connect(LOCAL, rec.proxy.port)
        try:
            yield rec, client
        finally:
            await client.close()


async def open_api(rec: Recording) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    """A connection to the recording's control API, on its socket or by TCP."""
    if rec.control_url.startswith("http://"):
        parts = urlsplit(rec.control_url)
        return await asyncio.open_connection(parts.hostname, parts.port)
    return await asyncio.open_unix_connection(rec.control_url)


async def send_raw(rec: Recording, raw: bytes, eof: bool = True) -> bytes:
    """``raw`` to the control API (then a FIN, if ``eof``); everything it answers until it closes."""
    reader, writer = await open_api(rec)
    try:
        writer.write(raw)
        if eof:  # a request cut short ends here rather than when the server tires of waiting
            writer.write_eof()
        return await asyncio.wait_for(reader.read(), WAIT)
    finally:
        writer.close()


def parse(answer: bytes) -> tuple[int, dict, dict]:
    head, _, body = answer.partition(b"\r\n\r\n")
    first, *lines = head.decode().split("\r\n")
    headers = {k.strip().lower(): v.strip() for k, _, v in (line.partition(":") for line in lines)}
    assert headers["content-type"] == "application/json" and int(headers["content-length"]) == len(body)
    assert headers["server"] == control_server.SIGNATURE  # every answer, errors too: how ctl knows the API
    return int(first.split()[1]), json.loads(body), headers


def credentials(rec: Recording) -> str:
    """The header lines a client of this API sends: its Host, and its token on TCP."""
    if not rec.control_url.startswith("http://"):
        return "Host: localhost\r\n"
    return f"Host: {urlsplit(rec.control_url).netloc}\r\nAuthorization: Bearer {rec.control_token}\r\n"


async def call(rec: Recording, method: str, path: str, body: object = None) -> tuple[int, dict]:
    """One request (``body`` as JSON, or bytes as they are); the status and the JSON answer."""
    data = body if isinstance(body, bytes) else b"" if body is None else json.dumps(body).encode()
    raw = (f"{method} {path} HTTP/1.1\r\n{credentials(rec)}Content-Type: application/json\r\n"
           f"Content-Length: {len(data)}\r\n\r\n").encode() + data
    status, answer, _ = parse(await send_raw(rec, raw))
    return status, answer


async def ok(rec: Recording, method: str, path: str, body: object = None, status: int = 200) -> dict:
    got, answer = await call(rec, method, path, body)
    assert got == status, answer
    return answer


async def until(check: Callable[[], object], what: str) -> None:
    for _ in range(int(WAIT * 100)):
        if check():
            return
        await asyncio.sleep(0.01)
    raise AssertionError(f"never: {what}")


async def held_frames(rec: Recording, count: int) -> list[dict]:
    """The held frames, once there are ``count`` of them."""
    for _ in range(int(WAIT * 100)):
        held = (await ok(rec, "GET", "/held"))["held"]
        if len(held) >= count:
            return held
        await asyncio.sleep(0.01)
    raise AssertionError(f"never {count} held frames")


async def answered(client: Client, channel: int) -> bool:
    """Whether a Sensor Request on ``channel`` gets its answer.  No timeout
    decides it: a request on channel 13 follows it, and the simulator answers
    in order, which the proxy keeps, so by 13's answer ``channel``'s is in or
    it never will be."""
    first = asyncio.create_task(client.sensor(channel, timeout=WAIT))
    await asyncio.sleep(0)  # the task sends its request before the one on channel 13
    await client.sensor(13, timeout=WAIT)
    await asyncio.sleep(0)  # the answer's dispatch wakes the task
    if first.done():
        await first
        return True
    first.cancel()
    return False


def strays(client: Client) -> list[bytes]:
    return [item.raw for item in client.stray]


def topic_text(by_topic: dict[str, list[dict]], topic: str, direction: str) -> bytes:
    """A topic's data of one direction as one byte string (base64 ``data`` fields)."""
    import base64

    return b"".join(base64.b64decode(m["data"]) for m in by_topic[topic] if m["dir"] == direction)


# -- faults while traffic flows ---------------------------------------------------------------------------


async def test_a_fault_is_added_switched_off_and_on_and_removed_while_traffic_flows(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        assert [await answered(client, 12) for _ in range(2)] == [True, True]
        fault = await ok(rec, "POST", "/faults", {"spec": DROP_EVERY_SECOND, "name": "lossy"}, 201)
        assert (fault["name"], fault["spec"], fault["enabled"], fault["hits"]) == ("lossy", DROP_EVERY_SECOND,
                                                                                 True, 0)
        assert [await answered(client, 12) for _ in range(4)] == [True, False, True, False]
        [listed] = (await ok(rec, "GET", "/faults"))["faults"]
        assert (listed["id"], listed["name"], listed["spec"], listed["hits"]) == \
            (fault["id"], "lossy", DROP_EVERY_SECOND, 2)
        off = await ok(rec, "POST", "/faults/lossy/enable", {"enabled": False})
        assert off["enabled"] is False
        assert [await answered(client, 12) for _ in range(2)] == [True, True]
        await ok(rec, "POST", f"/faults/{fault['id']}/enable", {"enabled": True})
        assert [await answered(client, 12) for _ in range(2)] == [True, False]
        assert (await ok(rec, "DELETE", "/faults/lossy"))["hits"] == 3
        assert (await ok(rec, "GET", "/faults"))["faults"] == []
        assert [await answered(client, 12) for _ in range(3)] == [True, True, True]
    drops = [i for i in read_all(str(tmp_path / "r.mcap"))["/interventions"] if i["action"] == "drop"]
    assert len(drops) == 3 and all(i["cause"] == f"fault lossy: {DROP_EVERY_SECOND}" for i in drops)
    assert all(i["before"].startswith("cr1-12--") and i["after"] == "" for i in drops)


# -- holding, editing, dropping ---------------------------------------------------------------------


async def test_a_held_request_released_edited_is_answered_on_the_edited_channel(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        assert (await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s kind:command"})) == \
            {"filter": "dir:c2s kind:command"}
        assert (await ok(rec, "GET", "/intercept"))["filter"] == "dir:c2s kind:command"
        asked = asyncio.create_task(client.sensor(13, timeout=WAIT))
        [held] = await held_frames(rec, 1)
        assert (held["conn"], held["dir"], held["kind"], held["text"]) == (1, "c2s", "command", "rr1-13--0--0-ss1")
        assert "intercept" in held["cause"] and held["waited_s"] >= 0
        released = await ok(rec, "POST", f"/held/{held['id']}/release", {"edit": "sensor 14"})
        assert released["text"] == "rr1-14--0--0-ss1"
        await until(lambda: any(s.startswith(b"cr1-14--") for s in strays(client)), "the answer on channel 14")
        assert (await ok(rec, "GET", "/held"))["held"] == [] and not asked.done()
        asked.cancel()
        assert (await ok(rec, "PUT", "/intercept", {"filter": ""}))["filter"] == ""
        assert await answered(client, 12)
    by_topic = read_all(str(tmp_path / "r.mcap"))
    [edit] = [i for i in by_topic["/interventions"] if i["action"] == "edit"]
    assert (edit["before"], edit["after"], edit["dir"]) == ("rr1-13--0--0-ss1", "rr1-14--0--0-ss1", "c2s")
    assert [i["action"] for i in by_topic["/interventions"]][:2] == ["hold", "edit"]
    delivered = topic_text(by_topic, "/tcp/delivered", "c2s")
    assert delivered.startswith(b"rr1-14--0--0-ss1rr1-12--0--0-ss1")  # the edit, then what came after it
    assert b"rr1-13--0--0-ss1" in topic_text(by_topic, "/tcp/reads", "c2s")  # what the client sent


async def test_held_frames_keep_their_order_and_a_dropped_one_never_arrives(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s kind:command"})
        first = asyncio.create_task(client.sensor(13, timeout=WAIT))
        second = asyncio.create_task(client.sensor(14, timeout=WAIT))
        one, two = await held_frames(rec, 2)
        assert (one["text"], two["text"]) == ("rr1-13--0--0-ss1", "rr1-14--0--0-ss1")
        await ok(rec, "POST", f"/held/{two['id']}/release")  # the later one first: it waits behind the other
        assert [h["id"] for h in (await ok(rec, "GET", "/held"))["held"]] == [one["id"]]
        [conn] = (await ok(rec, "GET", "/connections"))["connections"]
        assert conn["conn"] == 1 and conn["c2s_queued"] == 32 and not second.done()
        await ok(rec, "POST", f"/held/{one['id']}/release")
        await asyncio.wait_for(asyncio.gather(first, second), WAIT)
        third = asyncio.create_task(client.sensor(15, timeout=WAIT))
        [held] = await held_frames(rec, 1)
        dropped = await ok(rec, "POST", f"/held/{held['id']}/drop")
        assert dropped["text"] == "rr1-15--0--0-ss1"
        await ok(rec, "PUT", "/intercept", {"filter": ""})
        assert await answered(client, 12) and not third.done()
        third.cancel()
        [conn] = (await ok(rec, "GET", "/connections"))["connections"]
        assert conn["c2s_queued"] == 0  # the dropped frame's bytes are no longer counted as waiting
    by_topic = read_all(str(tmp_path / "r.mcap"))
    delivered = topic_text(by_topic, "/tcp/delivered", "c2s")
    assert delivered.startswith(b"rr1-13--0--0-ss1rr1-14--0--0-ss1") and b"rr1-15" not in delivered
    actions = [(i["action"], i["before"], i["held"]) for i in by_topic["/interventions"]]
    one_id, two_id = one["id"], two["id"]
    # a release is told when its frame is delivered (with where it went), so #14's after #13's
    assert actions == [("hold", "rr1-13--0--0-ss1", one_id), ("hold", "rr1-14--0--0-ss1", two_id),
                       ("release", "rr1-13--0--0-ss1", one_id), ("release", "rr1-14--0--0-ss1", two_id),
                       ("hold", "rr1-15--0--0-ss1", held["id"]), ("drop", "rr1-15--0--0-ss1", held["id"])]
    releases = [i for i in by_topic["/interventions"] if i["action"] == "release"]
    assert [delivered[r["delivered"]:r["delivered"] + 16] for r in releases] == [b"rr1-13--0--0-ss1",
                                                                                   b"rr1-14--0--0-ss1"]


async def test_a_forgotten_held_frame_is_released_by_the_hold_timeout(tmp_path):
    async with proxied(tmp_path / "r.mcap", hold_timeout=0.3) as (rec, client):
        await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s ch:13"})
        assert isinstance(await client.sensor(13, timeout=WAIT), int)  # nobody released it
        assert (await ok(rec, "GET", "/held"))["held"] == []
    [release] = [i for i in read_all(str(tmp_path / "r.mcap"))["/interventions"] if i["action"] == "release"]
    assert release["cause"].startswith("hold timeout after 0.3 s")


async def test_since_and_until_in_an_intercept_filter_count_from_the_connection_opening(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        await ok(rec, "PUT", "/intercept", {"filter": "since:600 dir:c2s ch:15"})
        assert await answered(client, 15)  # ten minutes after it opened: not yet
        await ok(rec, "PUT", "/intercept", {"filter": "until:600 dir:c2s ch:15"})
        asked = asyncio.create_task(client.sensor(15, timeout=WAIT))
        [held] = await held_frames(rec, 1)
        await ok(rec, "POST", f"/held/{held['id']}/release")
        await asyncio.wait_for(asked, WAIT)


async def test_release_all_lets_every_held_frame_go(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s"})
        asked = [asyncio.create_task(client.sensor(ch, timeout=WAIT)) for ch in (12, 13, 14)]
        await held_frames(rec, 3)
        assert await ok(rec, "POST", "/held/release-all") == {"released": 3}
        await asyncio.wait_for(asyncio.gather(*asked), WAIT)


# -- injection and the rules ---------------------------------------------------------------------------


async def test_an_injected_request_reaches_the_server_and_its_answer_the_client(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        [conn] = (await ok(rec, "GET", "/connections"))["connections"]
        sent = await ok(rec, "POST", "/inject", {"conn": conn["conn"], "dir": "c2s", "frame": "sensor 12"})
        assert sent == {"conn": 1, "dir": "c2s", "frame": "rr1-12--0--0-ss1"}
        # nobody asked, so the client keeps the answer as a stray item
        await until(lambda: any(s.startswith(b"cr1-12--") for s in strays(client)), "the injected request's answer")
        await ok(rec, "POST", "/inject", {"conn": 1, "dir": "s2c", "frame": "cr1-13--500--0-ss1"})
        await until(lambda: b"cr1-13--500--0-ss1" in strays(client), "the injected answer")
        assert await answered(client, 12)
    by_topic = read_all(str(tmp_path / "r.mcap"))
    injections = [(i["dir"], i["action"], i["after"]) for i in by_topic["/interventions"]]
    assert injections == [("c2s", "inject", "rr1-12--0--0-ss1"), ("s2c", "inject", "cr1-13--500--0-ss1")]
    request = b"rr1-12--0--0-ss1"  # injected, and then sent by the client once (answered())
    assert topic_text(by_topic, "/tcp/delivered", "c2s").startswith(request)
    assert topic_text(by_topic, "/tcp/delivered", "c2s").count(request) == 2
    assert topic_text(by_topic, "/tcp/reads", "c2s").count(request) == 1
    assert topic_text(by_topic, "/tcp/reads", "s2c").startswith(b"cr1-12--")  # the server's answer


async def test_a_typed_frame_that_breaks_a_rule_is_refused_unless_forced(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        status, answer = await call(rec, "POST", "/inject", {"conn": 1, "dir": "c2s", "frame": "rr1-99--0--0-ss1"})
        assert status == 400 and "PW-RANGE-CHANNEL" in answer["error"] and "force" in answer["error"]
        await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s ch:13"})
        asked = asyncio.create_task(client.sensor(13, timeout=WAIT))
        [held] = await held_frames(rec, 1)
        status, answer = await call(rec, "POST", f"/held/{held['id']}/release", {"edit": "sensor 99"})
        assert status == 400 and "PW-RANGE-CHANNEL" in answer["error"]
        assert [h["id"] for h in (await ok(rec, "GET", "/held"))["held"]] == [held["id"]]  # still held
        forced = await ok(rec, "POST", f"/held/{held['id']}/release", {"edit": "rr1-99--0--0-ss1", "force": True})
        assert forced["text"] == "rr1-99--0--0-ss1"
        await ok(rec, "POST", "/inject", {"conn": 1, "dir": "c2s", "frame": "rr1-99--0--0-ss1", "force": True})
        asked.cancel()
        await ok(rec, "PUT", "/intercept", {"filter": ""})
        assert await answered(client, 12)
    delivered = topic_text(read_all(str(tmp_path / "r.mcap")), "/tcp/delivered", "c2s")
    assert delivered.count(frame_from_text("rr1-99--0--0-ss1")) == 2


# -- every way a request can be wrong ---------------------------------------------------------------------


async def test_every_bad_request_answers_or_closes_and_the_proxy_goes_on(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        idle = await open_api(rec)  # a client that says nothing, all along
        cases = [
            (("GET", "/nowhere"), 404, "no such endpoint"),
            (("POST", "/faults", b"{not json"), 400, "not JSON"),
            (("POST", "/faults", b"[1, 2]"), 400, "JSON object"),
            (("POST", "/faults", {"name": "x"}), 400, "missing field 'spec'"),
            (("POST", "/faults", {"spec": 3}), 400, "'spec' must be a string"),
            (("POST", "/faults", {"spec": "explode dir:s2c"}), 400, "explode"),
            (("DELETE", "/faults/nosuch"), 404, "no fault 'nosuch'"),
            (("POST", "/faults/nosuch/enable", {"enabled": True}), 404, "no fault"),
            (("POST", "/faults/1/enable", {"enabled": "yes"}), 400, "true or false"),
            (("PUT", "/intercept", {}), 400, "missing field 'filter'"),
            (("PUT", "/intercept", {"filter": "since:soon"}), 400, "intercept filter"),
            (("POST", "/held/7/release"), 404, "no held frame #7"),
            (("POST", "/held/seven/drop"), 400, "a number"),
            (("POST", "/inject", {"conn": 9, "dir": "c2s", "frame": "sensor 1"}), 404, "no open connection #9"),
            (("POST", "/inject", {"conn": 1, "dir": "up", "frame": "sensor 1"}), 400, "c2s or s2c"),
            (("POST", "/inject", {"conn": True, "dir": "c2s", "frame": "sensor 1"}), 400, "whole number"),
            (("POST", "/inject", {"conn": 1, "dir": "c2s", "frame": "teleport 3"}), 400, "teleport"),
            # nested past Python's recursion limit, and past the API's own
            (("POST", "/faults", b"[" * 5000 + b"]" * 5000), 400, "not JSON"),
            (("PUT", "/intercept", {"filter": [[[[[[[[["x"]]]]]]]]]}), 400, "deeper than 8 levels"),
            # numbers past Python's int-string limit, and past 64 bits
            (("POST", f"/held/{'9' * 5000}/release"), 400, "at most 18 digits"),
            (("POST", "/inject", b'{"conn": ' + b"7" * 5000 + b', "dir": "c2s", "frame": "sensor 1"}'), 400,
             "not JSON"),
            (("POST", "/inject", {"conn": 2 ** 70, "dir": "c2s", "frame": "sensor 1"}), 400, "whole number"),
        ]
        for request, status, words in cases:
            got, answer = await call(rec, *request)
            assert (got, words in answer.get("error", "")) == (status, True), (request, got, answer)
        status, answer, headers = parse(await send_raw(rec, b"GET /inject HTTP/1.0\r\n\r\n"))
        assert status == 405 and headers["allow"] == "POST" and "takes POST" in answer["error"]
        json_head = "POST /faults HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
        big = f"{json_head}Content-Length: {MAX_BODY + 1}\r\n\r\n".encode()
        assert parse(await send_raw(rec, big))[0] == 413
        chunked = f"{json_head}Transfer-Encoding: chunked\r\n\r\n0\r\n\r\n".encode()
        assert parse(await send_raw(rec, chunked))[0] == 411
        for garbage in (b"\x16\x03\x01\x02\x00\x01\x00\x01\xfc\x03\x03\r\n", b"HELLO\r\n\r\n",
                        b"GET /state HTTP/1.1\r\nno colon here\r\n\r\n", b"GET /state HTTP/1.1\r\n\r\n",
                        b"GET /st", json_head.encode() + b"Content-Length: 10\r\n\r\n{",
                        json_head.encode() + b"Content-Length: " + b"9" * 5000 + b"\r\n\r\n"):
            answer = await send_raw(rec, garbage)
            assert answer == b"" or parse(answer)[0] == 400, garbage[:20]
        too_long = parse(await send_raw(rec, b"GET /" + b"x" * 70000 + b" HTTP/1.1\r\n"))
        assert too_long[0] == 431 and "not a request the control API takes" in too_long[1]["error"]
        assert await ok(rec, "GET", "/state")  # the idle client holds nothing up
        assert await answered(client, 12)  # nor did any of it touch the traffic
        idle[1].close()


async def test_a_client_that_stalls_is_cut_off_alone(tmp_path, monkeypatch):
    monkeypatch.setattr(control_server, "CLIENT_TIMEOUT_S", 0.2)
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        stalled = (b"POST /faults HTTP/1.1\r\nHost: localhost\r\nContent-Type: application/json\r\n"
                   b"Content-Length: 10\r\n\r\n{")
        answer = await send_raw(rec, stalled, eof=False)
        status, body, _ = parse(answer)
        assert status == 408 and "no complete request" in body["error"]
        assert await answered(client, 12)


async def test_stopping_ends_the_control_connections_still_open(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, _client):
        reader, writer = await open_api(rec)
        writer.write(b"GET /state HTTP/1.1\r\n")  # and never the rest
        socket_path = Path(rec.control_url)
        assert socket_path.is_socket()
        await rec.stop()
        try:  # the unread half request makes the close a reset
            assert await asyncio.wait_for(reader.read(), WAIT) == b""
        except ConnectionResetError:
            pass
        writer.close()
    assert read_all(str(tmp_path / "r.mcap"))["/tcp/events"]
    assert not socket_path.exists()  # the socket goes with the server


# -- whiztap ctl -------------------------------------------------------------------------------------------


async def ctl(rec: Recording, *args: str) -> Ran:
    """``whiztap ctl --control ... ARGS`` in a thread: the API answers in this test's loop."""
    return await asyncio.to_thread(run_cli, "ctl", "--control", rec.control_url, *args)


def line(result: Ran, code: int = 0) -> str:
    """The one line a command printed (stdout, or stderr when it failed)."""
    assert result.returncode == code, (result.stdout, result.stderr)
    text = result.stdout if code == 0 else result.stderr
    assert text.count("\n") == 1, text
    return text.strip()


async def test_ctl_drives_faults(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        added = line(await ctl(rec, "fault", "add", DROP_EVERY_SECOND, "--name", "lossy"))
        assert added.startswith("added fault #")
        assert "lossy  on  matched 0  hits 0  " + DROP_EVERY_SECOND + "  (drop, s2c," in added
        assert [await answered(client, 12) for _ in range(2)] == [True, False]
        assert "lossy  on  matched 2  hits 1" in line(await ctl(rec, "fault", "list"))
        listed = json.loads((await ctl(rec, "--format", "json", "fault", "list")).stdout)
        assert [(f["name"], f["hits"]) for f in listed["faults"]] == [("lossy", 1)]
        assert "lossy  off" in line(await ctl(rec, "fault", "off", "lossy"))
        assert [await answered(client, 12) for _ in range(2)] == [True, True]
        assert "lossy  on" in line(await ctl(rec, "fault", "on", "lossy"))
        assert line(await ctl(rec, "fault", "rm", "lossy")).startswith("removed fault #")
        assert line(await ctl(rec, "fault", "list")) == "no faults"
        assert line(await ctl(rec, "fault", "rm", "lossy"), 2) == "whiztap: no fault 'lossy' (see the fault list)"
        assert "explode" in line(await ctl(rec, "fault", "add", "explode dir:s2c"), 2)
        assert [await answered(client, 12) for _ in range(2)] == [True, True]


async def test_ctl_holds_releases_drops_and_injects(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, client):
        assert line(await ctl(rec, "intercept", "dir:c2s kind:command")) == "intercept: dir:c2s kind:command"
        assert line(await ctl(rec, "intercept")) == "intercept: dir:c2s kind:command"
        asked = asyncio.create_task(client.sensor(13, timeout=WAIT))
        await held_frames(rec, 1)
        assert line(await ctl(rec, "held")).startswith("#1 conn 1 c2s command rr1-13--0--0-ss1  (")
        refused = line(await ctl(rec, "release", "1", "--edit", "rr1-99--0--0-ss1"), 2)
        assert refused.startswith("whiztap: the frame breaks a rule (PW-RANGE-CHANNEL")
        assert refused.endswith("send it anyway with --force")  # ctl's option, not the API's field
        assert line(await ctl(rec, "release", "1")) == "released #1 as rr1-13--0--0-ss1"
        await asyncio.wait_for(asked, WAIT)
        second = asyncio.create_task(client.sensor(14, timeout=WAIT))
        await held_frames(rec, 1)
        assert line(await ctl(rec, "drop", "2")) == "dropped #2 rr1-14--0--0-ss1"
        assert line(await ctl(rec, "drop", "2"), 2).startswith("whiztap: no held frame #2")
        assert line(await ctl(rec, "release-all")) == "released 0 held frames"
        assert line(await ctl(rec, "intercept", "--off")) == "intercept: (off)"
        second.cancel()
        assert line(await ctl(rec, "inject", "1", "c2s", "sensor 12")) == "injected rr1-12--0--0-ss1 on #1 c2s"
        await until(lambda: any(s.startswith(b"cr1-12--") for s in strays(client)), "the injected request's answer")
        assert line(await ctl(rec, "connections")).startswith("#1 from 127.0.0.1:")
        state = (await ctl(rec, "state")).stdout.splitlines()
        assert state[0] == "intercept: (off)" and "faults: 0" in state and "connections: 1" in state
        as_json = json.loads((await ctl(rec, "--format", "json", "state")).stdout)
        assert set(as_json) == {"faults", "intercept", "held", "connections", "seed", "scripts", "verdict"}
        assert (await ctl(rec, "inject", "1", "sideways", "sensor 12")).returncode == 2


async def test_the_installed_command_answers_and_says_in_one_line_when_nothing_listens(tmp_path):
    async with proxied(tmp_path / "r.mcap") as (rec, _client):
        proc = await start_process("ctl", "--format", "json", "state", env={"WHIZTAP_CONTROL": rec.control_url})
        out, err = await asyncio.wait_for(proc.communicate(), WAIT)
        assert proc.returncode == 0, err
        assert json.loads(out)["connections"][0]["conn"] == 1
    port = closed_port()
    proc = await start_process("ctl", "--control", f"127.0.0.1:{port}", "fault", "list")
    out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    assert (proc.returncode, out) == (2, b"")
    assert err.decode() == (f"whiztap: cannot reach the control API at 127.0.0.1:{port}: connection refused; "
                            f"is 'whiztap record --control' running there?\n")
