"""Who can drive the control API (sniffer/mitm/control_guard.py,
control_server.py, control_endpoint.py): a web page in the user's browser
cannot (a browser's exact cross-site and DNS-rebinding requests are refused
with 403 and change nothing), a TCP client without the token cannot (401),
and the default Unix socket is the user's alone.  Bytes from outside, drawn
by hypothesis, never get past the guard nor make the server fail."""

from __future__ import annotations

import asyncio
import base64
import json
import os
import re
import signal
import socket
import stat
import tempfile
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.mitm.control_guard import check_head
from whiztap.sniffer.mitm.control_server import SIGNATURE, ControlServer
from whiztap.sniffer.mitm.controller import Controller
from whiztap.sniffer.mitm.http_api import HttpError
from whiztap.sniffer.record.record_run import MiddleSettings, StartError
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import run_cli, start_process
from tests.record_support import LOCAL, WAIT, read_all, recording
from tests.test_control_api import held_frames, ok, parse, send_raw

SERVO = "sr1-0--2000-ss1"  # what the page made the robot do
CHROME = ("User-Agent: Mozilla/5.0 (X11; Linux x86_64) AppleWebKit/537.36 (KHTML, like Gecko) "
          "Chrome/124.0.0.0 Safari/537.36\r\nAccept: */*\r\nAccept-Encoding: gzip, deflate, br, zstd\r\n"
          "Accept-Language: en-US,en;q=0.9\r\nConnection: keep-alive\r\n")


def browser(method: str, path: str, host: str, headers: str = "", body: bytes = b"", token: str | None = None) -> bytes:
    """A request as Chrome sends it from a page's fetch() or form (plus the
    control token, when the test wants to show that the other checks hold alone)."""
    auth = f"Authorization: Bearer {token}\r\n" if token else ""
    return (f"{method} {path} HTTP/1.1\r\nHost: {host}\r\n{CHROME}{headers}{auth}"
            f"Content-Length: {len(body)}\r\n\r\n").encode() + body


def attacks(host: str, rebound: str) -> list[tuple[str, bytes, str]]:
    """(what, the request as a page sends it, the words of its refusal); ``host``
    is the API's address, ``rebound`` the attacker's name re-pointed at it."""
    cross = "Origin: http://evil.example\r\nReferer: http://evil.example/\r\nSec-Fetch-Site: cross-site\r\n"
    inject = json.dumps({"conn": 1, "dir": "c2s", "frame": SERVO, "force": True}).encode()
    same = f"Origin: http://{rebound}\r\nSec-Fetch-Site: same-origin\r\nSec-Fetch-Mode: cors\r\n"
    return [
        ("cross-origin POST /inject as text/plain", browser(
            "POST", "/inject", host, cross + "Sec-Fetch-Mode: no-cors\r\nContent-Type: text/plain;charset=UTF-8\r\n",
            inject), "Origin 'http://evil.example'"),
        ("a form's POST /faults", browser(
            "POST", "/faults", host, cross + "Sec-Fetch-Mode: navigate\r\nSec-Fetch-Dest: document\r\n"
            "Content-Type: application/x-www-form-urlencoded\r\n", b"spec=drop+dir%3As2c&name=evil"), "Origin"),
        ("a form's POST /held/release-all", browser(
            "POST", "/held/release-all", host, cross + "Content-Type: application/x-www-form-urlencoded\r\n"),
         "Origin"),
        ("rebinding GET /state", browser("GET", "/state", rebound, "Sec-Fetch-Site: same-origin\r\n"),
         f"Host '{rebound}'"),
        ("rebinding PUT /intercept", browser("PUT", "/intercept", rebound, same + "Content-Type: application/json\r\n",
                                             b'{"filter": ""}'), f"Host '{rebound}'"),
        ("rebinding DELETE /faults/x", browser("DELETE", "/faults/x", rebound, same), f"Host '{rebound}'"),
    ]


async def test_a_browsers_cross_site_and_rebinding_requests_are_refused_and_change_nothing(tmp_path):
    path = tmp_path / "r.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim, \
            recording(sim.port, str(path), middle=MiddleSettings(control=Endpoint(host=LOCAL, port=0))) as rec:
        client = await Client.connect(LOCAL, rec.proxy.port)
        await ok(rec, "POST", "/faults", {"spec": "delay:1ms dir:c2s", "name": "x"}, 201)
        await ok(rec, "PUT", "/intercept", {"filter": "dir:c2s kind:command"})
        asked = asyncio.create_task(client.sensor(12, timeout=WAIT))
        [held] = await held_frames(rec, 1)
        before = await ok(rec, "GET", "/state")
        host = urlsplit(rec.control_url).netloc
        rebound = f"rebind.evil.example:{urlsplit(rec.control_url).port}"
        for token in (None, rec.control_token):  # with the token too: each check holds on its own
            for what, request, words in attacks(host, rebound):
                status, answer, _ = parse(await send_raw(rec, request))
                assert status == 403 and words in answer["error"], (what, token, status, answer)
        after = await ok(rec, "GET", "/state")
        assert (after["faults"], after["intercept"]) == (before["faults"], before["intercept"])
        assert [h["id"] for h in after["held"]] == [held["id"]]  # release-all did not happen
        await ok(rec, "POST", "/held/release-all")
        await asyncio.wait_for(asked, WAIT)
        await client.close()
    by_topic = read_all(str(path))
    assert [i["action"] for i in by_topic["/interventions"]] == ["hold", "delay", "release"]  # fault x's; no inject
    sent = b"".join(base64.b64decode(m["data"]) for m in by_topic["/tcp/delivered"] if m["dir"] == "c2s")
    assert SERVO.encode() not in sent  # nothing reached the robot


async def test_over_the_unix_socket_a_pages_origin_and_a_form_body_are_refused_too(tmp_path):
    async with Simulator(port=0, mode="vpn") as sim, \
            recording(sim.port, str(tmp_path / "r.mcap"), middle=MiddleSettings(control=Endpoint(path=""))) as rec:
        for what, request, words in attacks("localhost", "localhost")[:3]:
            status, answer, _ = parse(await send_raw(rec, request))
            assert status == 403 and words in answer["error"], (what, answer)
        form = browser("POST", "/faults", "localhost", "Content-Type: application/x-www-form-urlencoded\r\n",
                       b"spec=drop+dir%3As2c")
        status, answer, _ = parse(await send_raw(rec, form))
        assert status == 403 and "application/json" in answer["error"]
        assert (await ok(rec, "GET", "/faults"))["faults"] == []


async def test_tcp_takes_only_the_bearer_token(tmp_path):
    async with Simulator(port=0, mode="vpn") as sim, \
            recording(sim.port, str(tmp_path / "r.mcap"),
                      middle=MiddleSettings(control=Endpoint(host=LOCAL, port=0, token="s3cret-Token"))) as rec:
        assert rec.control_token == "s3cret-Token"
        host = urlsplit(rec.control_url).netloc
        for authorization in ("", "Authorization: Bearer wrong\r\n", "Authorization: Basic czNjcmV0LVRva2Vu\r\n",
                              "Authorization: Bearer s3cret-Token-and-more\r\n", "Authorization: Bearer\r\n"):
            raw = f"GET /state HTTP/1.1\r\nHost: {host}\r\n{authorization}\r\n".encode()
            status, answer, headers = parse(await send_raw(rec, raw))
            assert status == 401 and headers["www-authenticate"].startswith("Bearer"), (authorization, answer)
            assert "Authorization: Bearer TOKEN" in answer["error"]
        raw = f"GET /state HTTP/1.1\r\nHost: {host}\r\nAuthorization: bearer s3cret-Token\r\n\r\n".encode()
        assert parse(await send_raw(rec, raw))[0] == 200


@pytest.mark.parametrize(("bound", "host", "allowed"), [
    ("127.0.0.1", "127.0.0.1:7000", True), ("127.0.0.1", "localhost", True), ("127.0.0.1", "LOCALHOST:7000", True),
    ("127.0.0.1", "[::1]:7000", True), ("127.0.0.1", "[::1]", True), ("127.0.0.1", "127.0.0.1", True),
    ("127.0.0.1", "rebind.evil.example:7000", False), ("127.0.0.1", "127.0.0.1.evil.example", False),
    ("127.0.0.1", "localhost.evil.example:7000", False), ("127.0.0.1", "192.0.2.7:7000", False),
    ("192.0.2.7", "192.0.2.7:7000", True), ("robot-bench", "robot-bench:7000", True),
    ("0.0.0.0", "192.0.2.7:7000", True), ("0.0.0.0", "[2001:db8::1]:7000", True),
    ("0.0.0.0", "bench.example:7000", False), ("::", "rebind.evil.example", False),
])
def test_the_host_must_name_this_server_as_a_client_that_typed_its_address_does(bound, host, allowed):
    headers = {b"host": host.encode(), b"authorization": b"Bearer t"}
    if allowed:
        check_head(headers, Endpoint(host=bound, port=7000), "t")
    else:
        with pytest.raises(HttpError, match=f"Host '{re.escape(host)}' is not this server's address") as e:
            check_head(headers, Endpoint(host=bound, port=7000), "t")
        assert e.value.status == 403
    with pytest.raises(HttpError, match="must say Host"):
        check_head({}, Endpoint(host=bound, port=7000), "t")


# -- the Unix socket --------------------------------------------------------------------------------


@pytest.fixture
def short_dir():
    """A folder with a short path: a Unix socket's is at most 107 bytes."""
    folder = Path(tempfile.mkdtemp(prefix="wt-", dir="/tmp"))
    yield folder
    for path in folder.iterdir():
        path.unlink()
    folder.rmdir()


async def test_a_socket_path_taken_is_refused_and_a_stale_one_replaced(short_dir):
    controller = Controller()
    taken = ControlServer(controller, Endpoint(path=str(short_dir / "api.sock")))
    await taken.start()
    (short_dir / "file.sock").write_text("mine")
    stale = socket.socket(socket.AF_UNIX)
    stale.bind(str(short_dir / "stale.sock"))
    stale.close()
    try:
        for name, words in (("api.sock", "is served already (another whiztap?)"),
                            ("file.sock", "exists and is not a socket")):
            with pytest.raises(ValueError, match=re.escape(f"{short_dir / name} {words}; give another --control PATH")):
                await ControlServer(controller, Endpoint(path=str(short_dir / name))).start()
        again = ControlServer(controller, Endpoint(path=str(short_dir / "stale.sock")))
        await again.start()
        assert stat.S_IMODE(os.stat(again.url).st_mode) == 0o600
        await again.stop()
        assert not (short_dir / "stale.sock").exists()
    finally:
        await taken.stop()
    assert (short_dir / "file.sock").read_text() == "mine"


async def test_a_non_loopback_control_api_warns_and_a_bad_path_is_one_line(tmp_path, short_dir):
    from whiztap.sniffer.record.record_run import Recording, RecordSettings

    warned: list[str] = []
    async with Simulator(port=0, mode="vpn") as sim:
        wide = MiddleSettings(control=Endpoint(host="0.0.0.0", port=0))  # the case under test
        rec = Recording(RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(tmp_path / "a.mcap"), middle=wide),
                        warn=warned.append)
        await rec.start()
        await rec.stop()
        bad = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(tmp_path / "b.mcap"),
                             middle=MiddleSettings(control=Endpoint(path=str(short_dir / "no" / "such.sock"))))
        with pytest.raises(StartError, match=r"cannot serve the control API on .*such\.sock: No such file"):
            await Recording(bad).start()
    assert warned == [f"warning: the control API listens on 0.0.0.0:{urlsplit(rec.control_url).port}, which other "
                      f"machines may reach: whoever has its token can drop, edit and inject the traffic"]
    assert not (tmp_path / "b.mcap").exists()


@pytest.mark.slow
async def test_whiztap_record_prints_where_the_api_is_and_takes_its_socket_away(tmp_path, monkeypatch, short_dir):
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(short_dir))
    async with Simulator(port=0, mode="vpn") as sim:
        for control, token_line in ((["--control"], False), (["--control", "0.0.0.0:0"], True)):
            proc = await start_process("record", "--listen", "127.0.0.1:0", "--upstream", f"{LOCAL}:{sim.port}", "-q",
                                       "-o", tmp_path / f"r{len(control)}.mcap", *control)
            first = (await asyncio.wait_for(proc.stdout.readline(), WAIT)).decode()
            if token_line:
                m = re.search(r", control: http://0\.0\.0\.0:(\d+) token (\S+) \(Ctrl-C", first)
                assert m and len(m.group(2)) >= 32, first
                warning = (await asyncio.wait_for(proc.stderr.readline(), WAIT)).decode()
                assert warning.startswith(f"warning: the control API listens on 0.0.0.0:{m.group(1)}, which other")
            else:
                m = re.search(r", control: (/\S+\.sock) \(Ctrl-C", first)
                assert m and Path(m.group(1)).parent == short_dir / "whiztap", first
                sock = Path(m.group(1))
                assert stat.S_IMODE(sock.stat().st_mode) == 0o600 and stat.S_IMODE(sock.parent.stat().st_mode) == 0o700
            proc.send_signal(signal.SIGINT)
            _, err = await asyncio.wait_for(proc.communicate(), WAIT)
            assert proc.returncode == 0, err
    assert list((short_dir / "whiztap").iterdir()) == []  # the socket went with the recorder
    (short_dir / "whiztap").rmdir()


@pytest.mark.parametrize(("args", "words"), [
    (["--control", "--control-token", "abcdefgh"], "--control-token goes with a TCP --control [HOST:]PORT"),
    (["--control", "7000", "--control-token", "two words"], "--control-token may hold only letters"),
    (["--control", "host:port"], "--control needs a port number 0-65535, got 'host:port' (or a socket PATH)"),
])
def test_record_says_in_one_line_what_is_wrong_with_its_control_options(tmp_path, args, words):
    done = run_cli("record", "--upstream", "127.0.0.1:1", "-o", tmp_path / "r.mcap", *args)
    assert done.returncode == 2 and done.stderr.count("\n") == 1 and words in done.stderr, done.stderr
    assert not (tmp_path / "r.mcap").exists()


# -- bytes from outside ------------------------------------------------------------------------------

ANSWERED = {400, 401, 403, 404, 405, 411, 413, 431}
heads = st.builds(
    lambda method, path, lines, body: (f"{method} {path} HTTP/1.1\r\n" + "".join(f"{k}: {v}\r\n" for k, v in lines)
                                       + "\r\n").encode("latin-1") + body,
    st.sampled_from(["GET", "POST", "PUT", "DELETE", "PATCH", "get", "OPTIONS"]),
    st.sampled_from(["/state", "/faults", "/inject", "/held/release-all", "/faults/1", "/held/1/drop", "/x", "*"]),
    st.lists(st.tuples(st.sampled_from(["Host", "Origin", "Content-Type", "Content-Length", "Authorization",
                                        "Transfer-Encoding", "X-Other"]),
                       st.text(st.characters(min_codepoint=32, max_codepoint=126), max_size=30)), max_size=6),
    st.binary(max_size=64))


async def _throw(endpoint: Endpoint, raw: bytes) -> tuple[bytes, list]:
    """``raw`` to a control API of its own (a bare Controller); what it answered, and its faults after."""
    controller = Controller(report=lambda line: None)
    server = ControlServer(controller, endpoint)
    await server.start()
    try:
        if endpoint.unix:
            reader, writer = await asyncio.open_unix_connection(server.url)
        else:
            reader, writer = await asyncio.open_connection(LOCAL, server.endpoint.port)
        writer.write(raw)
        writer.write_eof()
        try:
            answer = await asyncio.wait_for(reader.read(), WAIT)
        except ConnectionResetError:
            answer = b""
        writer.close()
    finally:
        await server.stop()
    return answer, list(controller.faults)


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.one_of(heads, st.binary(max_size=200)))
def test_no_request_without_the_token_gets_past_the_guard_and_none_makes_the_server_fail(raw):
    answer, faults = asyncio.run(_throw(Endpoint(host=LOCAL, port=0, token="t" * 32), raw))
    assert faults == []
    if answer:
        status, _, headers = parse(answer)
        assert status in {400, 401, 403, 411, 431} and headers["server"] == SIGNATURE, (raw, answer)


@pytest.mark.slow
@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(raw=st.one_of(heads, st.binary(max_size=200)))
def test_any_bytes_on_the_socket_are_answered_in_json_never_with_a_500(raw):
    answer, _ = asyncio.run(_throw(Endpoint(path=""), raw))
    if answer:
        status, body, _ = parse(answer)
        assert status in ANSWERED | {200, 201} and isinstance(body, dict), (raw, answer)
