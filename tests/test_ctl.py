"""``whiztap ctl`` never talks to the wrong thing (sniffer/mitm/control_client.py):
pointed at a robot, at the proxy's --listen port, at another HTTP server or at
one that answers too much, too little or not JSON, it says so in one line
(exit status 2) and sends a robot that speaks first no byte.  And it finds
the control API itself, takes its token, and its options in any position.

All real: the simulator, a recording proxy, servers on 127.0.0.1 that speak
as a stranger would, and ctl run in-process (run_cli) in a thread."""

from __future__ import annotations

import asyncio
import contextlib
import json
import os
import re
import shutil
import socket
import tempfile
import threading
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from whiztap.sniffer.mitm import control_client
from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.record.record_run import MiddleSettings
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import Ran, run_cli
from tests.record_support import LOCAL, WAIT, read_all, recording

SIGNED = "HTTP/1.1 200 OK\r\nServer: whiztap/0.1.0\r\nContent-Type: application/json\r\n"


async def ctl(*args: str, env: dict[str, str] | None = None) -> Ran:
    """``whiztap ctl ARGS`` in a thread (the servers answer in this test's loop)."""
    return await asyncio.to_thread(run_cli, "ctl", *args, env=env)


def one_line(result: Ran) -> str:
    """The one line a failed ctl said on stderr, without its 'whiztap: '."""
    assert result.returncode == 2 and result.stdout == "", (result.returncode, result.stdout, result.stderr)
    assert result.stderr.count("\n") == 1, result.stderr
    return result.stderr.removeprefix("whiztap: ").rstrip("\n")


@pytest.fixture
def patient(monkeypatch: pytest.MonkeyPatch) -> None:
    """ctl listens longer before it speaks, so that a loaded machine cannot make
    a peer that speaks first look quiet; a peer that speaks ends the wait at once."""
    monkeypatch.setattr(control_client, "QUIET_S", 5.0)


class Stranger:
    """A TCP server that is not a control API: it says ``greeting`` on
    connecting (if any), and answers what it is sent with ``answer`` (bytes,
    or a generator of chunks), keeping every byte it received."""

    def __init__(self, answer: bytes | None = None, greeting: bytes = b"", stream: Iterator[bytes] | None = None,
                 hang_up: bool = False) -> None:
        self.answer, self.greeting, self.stream, self.hang_up = answer, greeting, stream, hang_up
        self.received = bytearray()
        self.port = 0
        self._server: asyncio.Server | None = None

    async def __aenter__(self) -> Stranger:
        self._server = await asyncio.start_server(self._serve, LOCAL, 0)
        self.port = self._server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        assert self._server is not None
        self._server.close()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            if self.hang_up:
                return
            writer.write(self.greeting)
            while b"\r\n\r\n" not in self.received:
                data = await reader.read(4096)
                if not data:
                    return
                self.received += data
            if self.answer is not None:
                writer.write(self.answer)
            for chunk in self.stream or ():
                writer.write(chunk)
                await writer.drain()
        except ConnectionError:
            pass  # the client stopped reading: what a bounded client does
        finally:
            writer.close()


# -- a peer that is not the control API --------------------------------------------------------------


async def test_ctl_pointed_at_a_robot_says_so_and_sends_it_nothing(patient):
    async with Simulator(port=0, mode="winsock", password="pw") as sim:
        port = sim.port
        said = one_line(await ctl("--control", f"127.0.0.1:{port}", "inject", "1", "c2s", "sensor 12"))
        for _ in range(int(WAIT * 100)):  # ctl hung up; the robot's end of it is over
            if sim.stats.open_connections == 0:
                break
            await asyncio.sleep(0.01)
    assert said == (f"127.0.0.1:{port} is not a whiztap control API (it sent 'sendchkpass'; "
                    f"is that the proxy's --listen port?)")
    assert (sim.stats.connections, sim.stats.bytes_in) == (1, 0)


@pytest.mark.slow
async def test_ctl_pointed_at_the_proxys_listen_port_says_so_and_the_recording_gets_no_http(tmp_path, patient):
    path = tmp_path / "r.mcap"
    async with Simulator(port=0, mode="winsock", password="pw") as sim:
        async with recording(sim.port, str(path)) as rec:
            port = rec.proxy.port
            said = one_line(await ctl("--control", f"127.0.0.1:{port}", "state"))
        bytes_in = sim.stats.bytes_in
    assert said == (f"127.0.0.1:{port} is not a whiztap control API (it sent 'sendchkpass'; "
                    f"is that the proxy's --listen port?)")
    by_topic = read_all(str(path))
    assert [r for r in by_topic.get("/tcp/reads", []) if r["dir"] == "c2s"] == []  # not a byte toward the robot
    assert any(r["dir"] == "s2c" for r in by_topic["/tcp/reads"]) and bytes_in == 0


async def test_ctl_pointed_at_another_http_server_sends_only_its_harmless_get():
    answer = b"HTTP/1.1 200 OK\r\nServer: nginx/1.25\r\nContent-Length: 2\r\n\r\n{}"
    async with Stranger(answer) as web:
        said = one_line(await ctl("--control", f"127.0.0.1:{web.port}", "fault", "add", "drop dir:s2c"))
    assert said == (f"127.0.0.1:{web.port} is not a whiztap control API (it answered HTTP 200 from "
                    f"'nginx/1.25', without whiztap's Server header)")
    assert web.received.startswith(b"GET /intercept HTTP/1.1\r\n") and b"POST" not in web.received


@pytest.mark.parametrize(("stranger", "words"), [
    (dict(hang_up=True), "it closed the connection before a word was said"),
    (dict(answer=b"sendchkpass"), "it answered 'sendchkpass', which is not HTTP"),
    (dict(answer=b"HTTP/1.1 200 OK\r\n\r\n"), "it answered HTTP 200, without whiztap's Server header"),
    (dict(answer=b""), "it closed the connection without an answer"),
])
async def test_ctl_says_in_one_line_what_a_stranger_did(stranger, words):
    async with Stranger(**stranger) as peer:
        said = one_line(await ctl("--control", f"127.0.0.1:{peer.port}", "held"))
    assert said == f"127.0.0.1:{peer.port} is not a whiztap control API ({words})"


# -- answers too long, too short, not JSON ----------------------------------------------------------------


def endless() -> Iterator[bytes]:
    chunk = b"ffff\r\n" + b"[" * 0xFFFF + b"\r\n"  # chunks of 64 KiB, for ever
    while True:
        yield chunk


@pytest.mark.parametrize(("stranger", "words"), [
    (dict(answer=SIGNED.encode() + b"Content-Length: 300000000\r\n\r\n", stream=endless()),
     "would answer 300000000 bytes, more than 16 MiB; not read"),
    (dict(answer=SIGNED.encode() + b"Transfer-Encoding: chunked\r\n\r\n", stream=endless()),
     "answered more than 16 MiB; stopped reading"),
    (dict(answer=SIGNED.encode() + b"Content-Length: 100\r\n\r\n{\"filter\""),
     "closed before its answer ended"),
    (dict(answer=SIGNED.encode() + b"Content-Length: 15\r\n\r\n<html>oops</ht>"),
     "answered something that is not JSON ('<html>oops</ht>')"),
    (dict(answer=SIGNED.encode() + b"Content-Length: 200000\r\n\r\n" + b"[" * 100000 + b"]" * 100000),
     "answered something that is not JSON ('" + "[" * 40 + "')"),
])
async def test_ctl_reads_an_answer_up_to_a_bound_and_says_what_was_wrong_with_it(stranger, words):
    async with Stranger(**stranger) as peer:
        said = one_line(await ctl("--control", f"127.0.0.1:{peer.port}", "state"))
    assert said == f"the control API at 127.0.0.1:{peer.port} {words}"


# -- finding the control API, and its token -------------------------------------------------------------


@pytest.fixture
def runtime(monkeypatch: pytest.MonkeyPatch) -> Iterator[Path]:
    """A runtime folder of this test's own (a short path: a socket's is at most
    107 bytes), and no WHIZTAP_CONTROL from the environment."""
    base = Path(tempfile.mkdtemp(prefix="wt-", dir="/tmp"))
    monkeypatch.setenv("XDG_RUNTIME_DIR", str(base))
    monkeypatch.delenv("WHIZTAP_CONTROL", raising=False)
    monkeypatch.delenv("WHIZTAP_CONTROL_TOKEN", raising=False)
    yield base / "whiztap"
    shutil.rmtree(base)


@contextlib.asynccontextmanager
async def proxies(tmp_path: Path, *controls: Endpoint) -> AsyncIterator[list]:
    """A recording proxy (in front of the simulator) per control endpoint."""
    async with Simulator(port=0, mode="vpn") as sim, contextlib.AsyncExitStack() as stack:
        yield [await stack.enter_async_context(recording(sim.port, str(tmp_path / f"r{n}.mcap"),
                                                         middle=MiddleSettings(control=control)))
               for n, control in enumerate(controls)]


@pytest.mark.slow
async def test_ctl_finds_the_one_control_api_running_for_the_user(tmp_path, runtime):
    assert one_line(await ctl("held")) == (f"no control API is running for you (none in {runtime}): start "
                                           f"'whiztap record --control', or say where one is with "
                                           f"--control PATH|[HOST:]PORT or WHIZTAP_CONTROL")
    async with proxies(tmp_path, Endpoint(path="")) as [rec]:
        assert Path(rec.control_url).parent == runtime
        assert oct(runtime.stat().st_mode & 0o777) == "0o700"
        assert oct(Path(rec.control_url).stat().st_mode & 0o777) == "0o600"
        # sockets nobody serves: one of a live process (pid 1: as if bound, not yet listening), one of a dead one
        dead = await asyncio.create_subprocess_exec("true")
        await dead.wait()
        stale = [socket.socket(socket.AF_UNIX) for _ in range(2)]
        for sock, pid in zip(stale, (1, dead.pid)):
            sock.bind(str(runtime / f"control-{pid}.sock"))
        result = await ctl("held")
        assert (result.returncode, result.stdout) == (0, "no held frames\n")  # neither counts
        async with proxies(tmp_path, Endpoint(path="")) as [other]:
            assert not (runtime / f"control-{dead.pid}.sock").exists()  # a new server swept the dead one's away
            names = ", ".join(sorted(Path(r.control_url).name for r in (rec, other)))
            assert one_line(await ctl("held")) == (f"2 control APIs are running ({names} in {runtime}): "
                                                   f"choose one with --control PATH")
            assert (await ctl("held", "--control", other.control_url)).returncode == 0
        for sock in stale:
            sock.close()
    assert list(runtime.iterdir()) == [runtime / "control-1.sock"]  # each server took its own socket away


async def test_a_runtime_folder_others_may_open_is_refused_by_ctl_and_by_the_server(tmp_path, runtime):
    runtime.mkdir(mode=0o700)
    os.chmod(runtime, 0o755)
    refusal = f"{runtime} is not a folder only you can open (owner uid {os.getuid()}, mode 755); " \
              f"remove it, or give --control PATH"
    assert one_line(await ctl("held")) == refusal
    with pytest.raises(Exception, match="cannot serve the control API: " + re.escape(refusal)):
        async with proxies(tmp_path, Endpoint(path="")):
            pass


@pytest.mark.slow
async def test_ctl_over_tcp_takes_the_token_printed_at_start(tmp_path, runtime):
    async with proxies(tmp_path, Endpoint(host=LOCAL, port=0)) as [rec]:
        where = rec.control_url.removeprefix("http://")
        assert rec.control_url.startswith("http://127.0.0.1:") and len(rec.control_token) >= 32
        assert one_line(await ctl("--control", rec.control_url, "held")) == (
            f"the control API at {where} takes a token: give the one 'whiztap record' printed with "
            f"--control-token or WHIZTAP_CONTROL_TOKEN")
        assert one_line(await ctl("--control", where, "--control-token", "guess", "held")) == (
            f"the control API at {where} refused the token given; give the one 'whiztap record' printed at start")
        by_env = await ctl("held", env={"WHIZTAP_CONTROL": rec.control_url, "WHIZTAP_CONTROL_TOKEN": rec.control_token})
        assert (by_env.returncode, by_env.stdout) == (0, "no held frames\n")
        after = await ctl("held", "--control", where, "--control-token", rec.control_token)
        assert (after.returncode, after.stdout) == (0, "no held frames\n")


@pytest.mark.slow
async def test_ctl_takes_its_options_before_or_after_the_subcommand(tmp_path, runtime):
    async with proxies(tmp_path, Endpoint(path="")) as [rec]:
        before = await ctl("--format", "json", "--control", rec.control_url, "held")
        after = await ctl("held", "--format", "json", "--control", rec.control_url)
        assert before.returncode == after.returncode == 0 and json.loads(before.stdout) == json.loads(after.stdout) \
            == {"held": []}
        nested = await ctl("fault", "--format", "json", "list", "--control", rec.control_url)
        assert json.loads(nested.stdout) == {"faults": []}
        assert (await ctl("--format", "json", "held", "--format", "text")).stdout == "no held frames\n"


# -- the TUI's proxy and the demo's -----------------------------------------------------------------------


@pytest.mark.slow
async def test_the_live_tui_and_the_demo_say_where_their_control_api_is(tmp_path, runtime):
    from whiztap.sniffer.record.record_run import RecordSettings
    from whiztap.tui.demo import run_headless
    from whiztap.tui.data.sources import LiveSource, ProxyRig

    async with Simulator(port=0, mode="vpn") as sim:
        middle = MiddleSettings(control=Endpoint(host=LOCAL, port=0), always=True)
        source = LiveSource(ProxyRig(RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(tmp_path / "live.mcap"),
                                                    quiet=True, middle=middle)), "live")
        await source.start()
        try:
            rec = source.recording
            assert source.title.endswith(f", control {rec.control_url} token {rec.control_token}")
            result = await ctl("--control", rec.control_url, "--control-token", rec.control_token, "held")
            assert (result.returncode, result.stdout) == (0, "no held frames\n")
        finally:
            await source.stop()
    said: list[str] = []
    await run_headless(str(tmp_path / "demo.mcap"), 0.2, middle=MiddleSettings(control=Endpoint(path="")),
                       announce=said.append)
    [line] = said
    assert line.startswith(f"control: {runtime}/control-") and line.endswith(".sock")
    assert list(runtime.iterdir()) == []


# -- bytes from outside, drawn ---------------------------------------------------------------------------


class _Answering:
    """A Unix socket server in a thread that answers each connection's request with ``answer``."""

    def __init__(self, folder: Path) -> None:
        self.path = str(folder / "peer.sock")
        self.answer = b""
        self._sock = socket.socket(socket.AF_UNIX)
        self._sock.bind(self.path)
        self._sock.listen(8)
        self._thread = threading.Thread(target=self._serve, daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while True:
            try:
                conn, _ = self._sock.accept()
            except OSError:
                return
            with conn:
                got = b""
                while b"\r\n\r\n" not in got:
                    data = conn.recv(4096)
                    if not data:
                        break
                    got += data
                with contextlib.suppress(OSError):
                    conn.sendall(self.answer)

    def close(self) -> None:
        self._sock.close()


@pytest.fixture(scope="module")
def answering() -> Iterator[_Answering]:
    folder = Path(tempfile.mkdtemp(prefix="wt-", dir="/tmp"))
    server = _Answering(folder)
    yield server
    server.close()
    shutil.rmtree(folder)


answers = st.one_of(
    st.binary(max_size=300),
    st.builds(lambda status, headers, body: f"HTTP/1.1 {status} X\r\n{headers}\r\n".encode() + body,
              st.integers(100, 999),
              st.lists(st.sampled_from(["Server: whiztap/0.1.0", "Content-Length: 2", "Content-Length: 99",
                                        "Transfer-Encoding: chunked", "Content-Type: application/json",
                                        "Server: other"]), max_size=4).map(lambda h: "".join(x + "\r\n" for x in h)),
              st.one_of(st.binary(max_size=100),
                        st.sampled_from([b"{}", b'{"error": "no"}', b"[1]", b"2\r\n{}\r\n0\r\n\r\n"]))))


@pytest.mark.slow
@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(answer=answers)
def test_whatever_a_peer_answers_ctl_says_one_line_or_takes_json(answering, answer):
    """The client's only outcomes: the answer's JSON, or ControlClientError
    (which ctl shows as one line); never another exception."""
    answering.answer = answer
    client = control_client.ControlClient(Endpoint(path=answering.path))
    try:
        client.call("GET", "/state")
    except control_client.ControlClientError as e:
        assert "\n" not in str(e) and str(e)
