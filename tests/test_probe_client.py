"""``whiztap probe client``: whiztap plays the server, the client under test runs once per case.

Real processes and sockets: whiztap's own ``client`` (which passes every
case) and tests/buggy_client.py (each planted defect caught by the case
meant for it, with the rule that names it) run as the command under test;
the cases' byte-level pieces (cuts, stray bytes, the padded picture, the
standard-error watch) are properties over any bytes.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import random
import re
import shlex
import socket
import sys
import time
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.probe.client_cases import (
    GARBAGE_ALPHABET, LARGEST_IMAGE, Cut, Schedule, Shaper, catalogue, catalogue_table, cut, field_cuts, pad_jpeg)
from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.analyzer.protocol.observations import may_tell
from whiztap.analyzer.protocol.rules import RULES
from whiztap.sniffer.probe.client_run import (
    MAX_QUEUED, STDERR_TAIL, TRACEBACK, ClientProbe, PlayedServer, _watch_stderr)
from whiztap.sniffer.sim.camera import render_frame
from whiztap.sniffer.sim.robot import ServerMode

from tests.buggy_client import BUGS
from tests.cli_support import WHIZTAP, run_cli
from tests.outputs import SECRET, assert_no_leak

BUGGY = Path(__file__).with_name("buggy_client.py")
DOCS = Path(__file__).parents[1] / "docs" / "probe.md"
ALL = [case.id for case in catalogue()]
TIMEOUT = "2"  # a case's wait in these tests: the clients here give up on a server after 1 s or less
# whiztap's own client: the password from the probe's variable, three requests that have answers
# --timeout: six times the slow server's delay (0.25 s): with 0.5 s the slow case
# failed once when make test ran six test processes on two cores
OWN_CLIENT = ("sh -c 'printf \"config\\nsensor 12\\nservo 3\\ncamera\\n\" | "
              f"WHIZTAP_PASSWORD=\"$WHIZTAP_PROBE_PASSWORD\" {WHIZTAP} client --timeout 1.5 {{host}}:{{port}}'")
OWN_VPN_CLIENT = f"sh -c 'printf \"config\\nsensor 12\\n\" | {WHIZTAP} client --timeout 1.5 {{host}}:{{port}}'"


def buggy(bug: str | None = None) -> str:
    return f"{shlex.quote(sys.executable)} {BUGGY}{f' --bug {bug}' if bug else ''} {{host}} {{port}}"


def probe(*args: str, env: dict[str, str | None] | None = None):
    return run_cli("probe", "client", "--timeout", TIMEOUT, *args, env=env)


def report(*args: str) -> tuple[int, dict]:
    done = probe("--format", "json", *args)
    assert done.returncode in (0, 1), done.stderr
    return done.returncode, json.loads(done.stdout)


def verdicts(data: dict) -> dict[str, tuple[str, list[str]]]:
    return {c["id"]: (c["verdict"], [v["rule"] for v in c["violations"]]) for c in data["cases"]}


# -- whiztap's own client passes -------------------------------------------------------------------


@pytest.mark.slow  # the whole catalogue: the slow and the idle server take a second each
def test_whiztaps_own_client_passes_every_case():
    status, data = report("--run", OWN_CLIENT)
    assert {c["id"]: c["verdict"] for c in data["cases"]} == dict.fromkeys(ALL, "pass"), data
    assert status == 0 and (data["passed"], data["failed"], data["skipped"]) == (len(ALL), 0, 0)
    assert data["role"] == "client" and data["mode"] == "winsock" and data["target"] == OWN_CLIENT


def test_whiztaps_own_client_passes_in_vpn_mode_and_the_handshake_case_is_skipped_with_its_reason():
    status, data = report("--run", OWN_VPN_CLIENT, "--mode", "vpn",
                          "--cases", "session.baseline,split.*,handshake.*,close.mid-session")
    cases = {c["id"]: c for c in data["cases"]}
    assert status == 0
    assert {i: c["verdict"] for i, c in cases.items()} == {
        "session.baseline": "pass", "handshake.failed-validation": "skip", "split.bytes": "pass",
        "split.fields": "pass", "close.mid-session": "pass"}
    assert "VPN" in cases["handshake.failed-validation"]["reason"]


def test_a_case_the_client_gives_nothing_to_act_on_is_skipped_with_the_reason():
    """whiztap's client asking only for the configuration never asks for a picture."""
    only_config = f"{WHIZTAP} client --timeout 0.5 {{host}}:{{port}} config"
    status, data = report("--run", f"sh -c 'WHIZTAP_PASSWORD=\"$WHIZTAP_PROBE_PASSWORD\" exec {only_config}'",
                          "--cases", "camera.largest")
    assert status == 0 and data["cases"][0]["verdict"] == "skip"
    assert "Fetch Camera Image" in data["cases"][0]["reason"]


# -- each planted defect caught by its case ----------------------------------------------------------


SLOW = {bug for bug, (_, case, rule) in BUGS.items() if rule == "PROBE-CLIENT-HANG" or case == "slow.answers"}


@pytest.mark.parametrize("bug", [pytest.param(b, marks=pytest.mark.slow) if b in SLOW else b for b in BUGS])
def test_each_planted_client_defect_is_caught_by_its_case(bug):
    _, case, rule = BUGS[bug]
    status, data = report("--run", buggy(bug), "--cases", case)
    assert status == 1
    assert verdicts(data)[case] == ("fail", [rule]), data


@pytest.mark.slow  # the slow server's case takes a second
def test_the_buggy_client_without_a_bug_passes_the_cases_that_catch_them():
    """So what each case caught is the defect, not the test client."""
    cases = sorted({case for _, case, _ in BUGS.values()} - {"idle.server"})
    status, data = report("--run", buggy(), "--cases", ",".join(cases))
    assert status == 0 and {c["verdict"] for c in data["cases"]} == {"pass"}, data


@pytest.mark.slow  # the wait runs out: 2 s
def test_a_hung_client_is_killed_with_its_whole_process_group(tmp_path):
    """A shell pipeline's children too: nothing the client started outlives its case."""
    pid_file = tmp_path / "child.pid"
    status, data = report("--run", f"sh -c 'sleep 300 & echo $! > {pid_file}; wait'", "--cases", "session.baseline")
    assert status == 1 and verdicts(data)["session.baseline"] == ("fail", ["PROBE-CLIENT-HANG"])
    child = int(pid_file.read_text())
    state = Path(f"/proc/{child}/stat")

    def dead() -> bool:  # gone, or a zombie awaiting its parent
        try:
            return state.read_text().split()[2] == "Z"
        except FileNotFoundError:
            return True

    # SIGKILL to a group is delivered, not awaited: on a loaded machine the
    # sleeper may still be scheduled for a moment after the run returns.
    deadline = time.monotonic() + 10
    while not dead() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert dead(), state.read_text()


def test_a_client_killed_by_a_signal_is_a_crash_and_one_that_never_connects_says_so():
    status, data = report("--run", "sh -c 'kill -SEGV $$'", "--cases", "session.baseline")
    assert status == 1
    rules = {v["rule"]: v["detail"] for v in data["cases"][0]["violations"]}
    assert rules.keys() == {"PROBE-CLIENT-CRASH", "PROBE-CLIENT-NO-CONNECTION"}
    assert "SIGSEGV" in rules["PROBE-CLIENT-CRASH"]


# -- what the client gets, and the password -----------------------------------------------------------


def test_the_client_gets_host_port_case_and_password_in_its_environment_never_on_its_command_line(tmp_path):
    seen = tmp_path / "env"
    show = (f"sh -c 'echo \"$0 $1 $WHIZTAP_PROBE_HOST $WHIZTAP_PROBE_PORT $WHIZTAP_PROBE_CASE "
            f"$WHIZTAP_PROBE_PASSWORD\" > {seen}' {{host}} {{port}}")
    probe("--run", show, "--cases", "session.baseline", "--password", "pw-1")
    host, port, env_host, env_port, case, password = seen.read_text().split()
    assert (host, env_host, case, password) == ("127.0.0.1", "127.0.0.1", "session.baseline", "pw-1")
    assert port == env_port and int(port) > 0


@pytest.mark.parametrize("fmt", ["text", "json", "junit", "markdown", "html"])
def test_the_password_never_shows_in_the_report_even_when_the_client_prints_it(fmt):
    """A client that prints the password on its way out (and sends it, as any
    winsock client does): its last line is quoted in the finding, masked."""
    secret = SECRET.decode()
    tell = "sh -c 'echo \"no luck with $WHIZTAP_PROBE_PASSWORD\" >&2; exit 3'"
    done = probe("--run", tell, "--cases", "session.baseline", "--password", secret, "--format", fmt)
    assert done.returncode == 1
    assert_no_leak(f"probe client --format {fmt}", done.stdout + done.stderr)
    sent = probe("--run", buggy("sensor-out-of-range"), "--cases", "session.baseline", "--password", secret,
                 "--format", fmt)
    assert_no_leak(f"probe client --format {fmt} (a client that sends it)", sent.stdout + sent.stderr)


# -- bad input -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(("args", "says"), [
    ((), "--run"),
    (("--run", "   "), "--run"),
    (("--run", "client 'unclosed"), "--run"),
    (("--run", "/nonexistent/client {host} {port}"), "cannot start"),
    (("--run", "true", "--cases", "no-such-case"), "--cases"),
    (("--run", "true", "--password", ""), "--password"),
])
def test_bad_input_is_one_line_and_status_2(args, says):
    done = probe(*args)
    assert done.returncode == 2, done
    assert done.stderr.count("\n") == 1 and says in done.stderr and "Traceback" not in done.stderr
    assert "unexpected error" not in done.stderr


def test_list_prints_the_catalogue_without_running_anything():
    done = run_cli("probe", "client", "--list")
    assert done.returncode == 0 and done.stdout == catalogue_table(catalogue())


def test_the_docs_show_the_catalogue_the_code_has():
    text = DOCS.read_text()
    section = text[text.index("## probe client"):]
    assert catalogue_table(catalogue()) in section


# -- the schedules' byte-level pieces --------------------------------------------------------------------


@given(st.binary(max_size=200), st.sampled_from(list(Cut)))
def test_a_cut_reply_is_the_reply(data, how):
    assert b"".join(cut(data, how)) == data
    assert all(cut(data, how))


@given(st.integers(0, 23), st.integers(0, 8000))
def test_field_cuts_fall_on_every_field_boundary(channel, value):
    frame = f"cr1-{channel}--{value}--0-ss1".encode()
    assert field_cuts(frame) == [b"cr1-", str(channel).encode(), b"--", str(value).encode(), b"--", b"0", b"-ss1"]


@given(st.binary(max_size=64), st.booleans(), st.integers(0, 2**32))
def test_stray_bytes_never_join_the_answer_they_precede(data, answer, seed):
    reply = b"cr1-12--100--0-ss1"
    shaper = Shaper(Schedule(garbage=True), seed)
    shaped = b"".join(shaper.shape(reply, True) or [])
    assert shaped.endswith(reply) and set(shaped[:-len(reply)]) <= set(GARBAGE_ALPHABET)
    items = Framer().feed(shaped, 0)
    assert [i.kind for i in items] == [ItemKind.UNFRAMED, ItemKind.RESPONSE] and items[1].raw == reply
    assert not any(may_tell(bytes([b])) for b in GARBAGE_ALPHABET)


@settings(max_examples=25)
@given(st.one_of(st.just(0), st.integers(4, 300_000)))
def test_a_padded_picture_has_exactly_its_size_and_stays_one_image(extra):
    jpeg = render_frame(1, 0.0)
    padded = pad_jpeg(jpeg, len(jpeg) + extra)
    assert len(padded) == len(jpeg) + extra
    items = Framer().feed(padded, 0)
    assert [(i.kind, len(i.raw)) for i in items] == [(ItemKind.IMAGE, len(padded))]


def test_the_largest_picture_is_one_item_for_the_analyzer():
    padded = pad_jpeg(render_frame(1, 0.0), LARGEST_IMAGE)
    framer = Framer()
    items = [i for n in range(0, len(padded), 1 << 16) for i in framer.feed(padded[n:n + (1 << 16)], 0)]
    assert [(i.kind, len(i.raw)) for i in items] == [(ItemKind.IMAGE, LARGEST_IMAGE)]


@given(st.binary(max_size=300), st.booleans(), st.randoms(use_true_random=False))
def test_a_traceback_is_seen_however_standard_error_is_cut(noise, with_traceback, rng):
    stream = noise + (TRACEBACK + b"\nValueError: x\n" if with_traceback else b"") + noise
    assert asyncio.run(_watched(stream, rng)) == (TRACEBACK in stream, stream[-STDERR_TAIL:])


async def _watched(stream: bytes, rng: random.Random) -> tuple[bool, bytes]:
    reader = asyncio.StreamReader()
    cuts = sorted(rng.sample(range(len(stream) + 1), min(len(stream), 5)))
    for a, b in zip([0, *cuts], [*cuts, len(stream)], strict=True):
        if b > a:
            reader.feed_data(stream[a:b])
    reader.feed_eof()
    return await _watch_stderr(reader)


QUICK_CASES = [c for c in catalogue() if not c.schedule.delay_s]


@settings(max_examples=40, deadline=None)
@given(st.sampled_from(QUICK_CASES), st.sampled_from(["winsock", "vpn"]),
       st.lists(st.one_of(st.binary(max_size=40), st.sampled_from(
           [b"pw", b"rr1-24--0--0-ss1", b"rr1-12--0--0-ss1", b"rr1-29--0--0-ss1", b"sr1-25--", b"\r\n"])),
           max_size=8))
def test_whatever_a_client_sends_the_played_server_judges_it_and_ends(case, mode, pieces):
    """Bytes from outside: any client's, in any reads, on any schedule; no
    error escapes a connection and every finding is one of the analyzer's rules."""
    findings = asyncio.run(_play(case, mode, pieces))
    assert set(findings) <= RULES.keys()


async def _play(case, mode: str, pieces: list[bytes]) -> list[str]:
    server = PlayedServer(ClientProbe("any", mode=ServerMode(mode), password="pw"), case)
    await server.start()
    try:
        reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
        for piece in pieces:
            writer.write(piece)
            await writer.drain()
        writer.write_eof()
        with contextlib.suppress(ConnectionError):
            await reader.read()  # until the server closes its side
        writer.close()
    finally:
        await server.finish()
    return [f.rule for f in server.findings()]


# -- memory ---------------------------------------------------------------------------------------------


@pytest.mark.slow  # filling the socket's buffers takes a second or two
async def test_a_client_that_floods_and_never_reads_fills_no_memory():
    """Requests sent as fast as the socket takes them to a slow server, never
    reading an answer: the replies waiting stay within MAX_QUEUED, because the
    server stops reading until they are out (the client's writes then block)."""
    case = next(c for c in catalogue() if c.id == "slow.answers")
    server = PlayedServer(ClientProbe("flood", password="pw"), case)
    await server.start()
    reader, writer = await asyncio.open_connection("127.0.0.1", server.port)
    writer.transport.get_extra_info("socket").setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)
    await reader.readexactly(len(b"sendchkpass"))
    writer.write(b"pw")
    chunk = b"rr1-12--0--0-ss1" * 4096  # 64 KiB of Sensor Requests
    try:
        while True:  # until the server stops reading: the socket's buffers fill and drain() waits
            writer.write(chunk)
            done, _ = await asyncio.wait({asyncio.ensure_future(writer.drain())}, timeout=1.0)
            if not done:
                break
        connection = server.connections[0]
        assert connection._queue.qsize() <= MAX_QUEUED
        assert len(connection.violations) <= 1
    finally:
        writer.transport.abort()
        await server.finish()


def test_every_case_has_a_unique_id_a_spec_section_and_a_title():
    ids = [c.id for c in catalogue()]
    assert len(set(ids)) == len(ids) and all(re.fullmatch(r"[a-z0-9-]+\.[a-z0-9-]+", i) for i in ids)
    assert all(c.spec and c.title for c in catalogue())
