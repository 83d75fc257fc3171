"""`whiztap sim` and `whiztap client`: the simulator as a process of its own (signals
end it), the client's commands run in this process, and the client's command
language in-process."""

from __future__ import annotations

import re
import signal
import socket
import subprocess
import sys

import pytest

from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.sniffer.sim.client import Client, ResponseTimeout
from whiztap.sniffer.sim.console import CommandError, run, split_line
from whiztap.sniffer.sim.simulator import Simulator

from tests.cli_support import WHIZTAP, Ran, run_cli

LISTENING = re.compile(r"listening on 127\.0\.0\.1:(\d+)")


def start_sim(*args: str) -> tuple[subprocess.Popen, int]:
    proc = subprocess.Popen([WHIZTAP, "sim", "--port", "0", *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    line = proc.stdout.readline()
    match = LISTENING.search(line)
    if match is None:
        proc.kill()
        raise AssertionError(f"no port announced: {line!r} {proc.stderr.read()!r}")
    return proc, int(match[1])


def stop(proc: subprocess.Popen, sig: int = signal.SIGTERM) -> tuple[int, str]:
    proc.send_signal(sig)
    try:
        _, err = proc.communicate(timeout=20)
    except subprocess.TimeoutExpired:
        proc.kill()
        raise
    return proc.returncode, err


def free_port() -> int:
    """A port nothing listens on (bound, then released)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def one_line_error(result: Ran, text: str) -> None:
    assert result.returncode == 2, result
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("whiztap: "), result.stderr
    assert text in result.stderr and "Traceback" not in result.stderr


@pytest.fixture(scope="module")
def sim_port():
    proc, port = start_sim("--password", "hunter2", "-q")
    yield port
    stop(proc)


# -- whiztap sim ---------------------------------------------------------------------------------


def test_sim_prints_its_port_and_serves_the_client(sim_port):
    result = run_cli("client", f"127.0.0.1:{sim_port}", "--password", "hunter2", "config")
    assert result.returncode == 0, result.stderr
    assert result.stdout == ("Configuration Settings: 24 channels: "
                             "servo:0-5,switch:6-8,switch1:9-11,sensor:12-23\n")


def test_client_takes_a_command_quoted_or_as_words(sim_port):
    address = f"127.0.0.1:{sim_port}"
    quoted = run_cli("client", address, "-p", "hunter2", "servo 3 1500")
    words = run_cli("client", address, "-p", "hunter2", "servo", "3", "1500")
    frame = run_cli("client", address, "-p", "hunter2", "raw rr1-3--1500--0-ss1")
    assert quoted.returncode == words.returncode == frame.returncode == 0, (quoted.stderr, words.stderr, frame.stderr)
    assert quoted.stdout == words.stdout == "Normal Send: channel 3 -> 1500\n"
    assert frame.stdout.startswith("sent 18 bytes\n"), frame.stdout


def test_sim_options_shape_the_server():
    proc, port = start_sim("--mode", "vpn", "--channels", "sensor:0-1,servo:2", "--camera", "none", "-q")
    try:
        config = run_cli("client", f"127.0.0.1:{port}", "config", "--timeout", "5")
        camera = run_cli("client", f"127.0.0.1:{port}", "camera", "--timeout", "0.3")
    finally:
        stop(proc)
    assert config.stdout == "Configuration Settings: 3 channels: sensor:0-1,servo:2\n"
    one_line_error(camera, "no answer to Fetch Camera Image")


def test_ctrl_c_stops_the_server_as_its_normal_end_like_record_and_stub():
    """One convention (README): Ctrl-C or SIGTERM ends a server or recorder, exit 0."""
    proc, port = start_sim("-q")
    with socket.create_connection(("127.0.0.1", port)) as open_client:
        assert open_client.makefile("rb").read(11) == b"sendchkpass"
        status, err = stop(proc, signal.SIGINT)
    assert (status, err) == (0, "")


def test_sigterm_stops_cleanly():
    proc, _ = start_sim("-q")
    assert stop(proc) == (0, "")


def test_sim_port_in_use_is_one_line():
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        one_line_error(run_cli("sim", "--port", str(port)), f"cannot listen on 127.0.0.1:{port}")


@pytest.mark.parametrize("args, text", [
    (["--channels", "servo:0-3,sensor:5"], "--channels: channel 4 has no unit"),
    (["--password", ""], "needs a non-empty --password"),
])
def test_sim_bad_options_are_one_line(args, text):
    one_line_error(run_cli("sim", "--port", "0", *args), text)


# -- whiztap client ---------------------------------------------------------------------------------


def test_client_to_an_unreachable_port_is_one_line():
    port = free_port()
    one_line_error(run_cli("client", f"127.0.0.1:{port}", "config"), f"cannot connect to 127.0.0.1:{port}")


@pytest.mark.parametrize("address, text", [
    ("nowhere", "the server address must be HOST:PORT, got 'nowhere'"),
    ("127.0.0.1:x", "the server address needs a port number 0-65535, got '127.0.0.1:x'"),
    ("127.0.0.1:70000", "needs a port number 0-65535"), (":5000", "must be HOST:PORT"),
])
def test_client_bad_address_is_one_line(address, text):
    one_line_error(run_cli("client", address, "config"), text)


def test_client_wrong_or_missing_password_is_one_line(sim_port):
    one_line_error(run_cli("client", f"127.0.0.1:{sim_port}", "-p", "nope", "config"), "Failed Validation")
    one_line_error(run_cli("client", f"127.0.0.1:{sim_port}", "config"), "asks for a password")


def test_client_camera_writes_a_jpeg(sim_port, tmp_path):
    target = tmp_path / "pic.jpg"
    result = run_cli("client", f"127.0.0.1:{sim_port}", "camera", "-o", str(target), "-p", "hunter2")
    assert result.returncode == 0, result.stderr
    image = target.read_bytes()
    assert re.fullmatch(rf"camera: {len(image)} bytes jpeg, saved to .*pic.jpg\n", result.stdout)
    assert [i.kind for i in Framer().feed(image, 0)] == [ItemKind.IMAGE]


def test_client_reads_commands_from_stdin(sim_port):
    script = "servo 4 1800\nservo 4\n# a comment\n\nswitch 7 on\nbogus\nrr1-0--0--2-ss1\nquit\nsensor 12\n"
    result = run_cli("client", f"127.0.0.1:{sim_port}", "-p", "hunter2", stdin=script)
    assert result.returncode == 1  # one command failed
    lines = result.stdout.splitlines()
    assert lines[0] == "Normal Send: channel 4 -> 1800"
    assert re.fullmatch(r"servo 4 position [\d.]+ \(data \d+\)", lines[1])
    assert lines[2:] == ["switch 7 on", "sent 15 bytes", "< cr1-0--4000--0-ss1  Response ch 0 data 4000"]
    assert result.stderr == "error: unknown command 'bogus'; try 'help'\n"


def test_help_is_fast_to_load():
    code = ("import sys, whiztap.sniffer.cli.sim; "
            "print(sorted(m for m in ('PIL', 'textual', 'scapy', 'whiztap.sniffer.sim.simulator') "
            "if m in sys.modules))")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=30)
    assert result.stdout == "[]\n", result.stderr
    listing = run_cli("--help").stdout
    assert re.search(r"^\s+client\s", listing, re.M) and re.search(r"^\s+sim\s", listing, re.M)


# -- the command language, in-process ----------------------------------------------------------------


@pytest.fixture
async def session():
    async with Simulator(mode="vpn", clock=lambda: 0) as sim:
        async with await Client.connect("127.0.0.1", sim.port, timeout=2) as client:
            yield sim, client


async def test_every_command(session, tmp_path):
    sim, client = session
    robot = sim.robot
    said = {}
    for line in ["config", "sensor 12", "servo 3", "servo 3 1500", "send 2 700", "switch 7 on", "switch 8 on",
                 "switch 8 off", "script 120", "script 272", "setconfig servo:0-1", "sleep 0",
                 f"camera -o {tmp_path / 'x.jpg'}", "camera", "raw rr1-0--0--2-ss1\\r\\n"]:
        said[line] = await run(client, split_line(line))
    assert said["sensor 12"] == f"sensor 12 = {robot.sensor_value(12, 0)}"
    assert said["servo 3"] == "servo 3 position 1000 (data 4000)"
    assert said["script 120"] == "play internal script 120"
    assert said["script 272"] == "play external script 272"
    assert said["setconfig servo:0-1"] == "Set Configuration: 2 entries sent"
    assert said["raw rr1-0--0--2-ss1\\r\\n"].splitlines()[1] == "< cr1-0--4000--0-ss1  Response ch 0 data 4000"
    assert said["camera"].startswith("camera: ") and (tmp_path / "x.jpg").read_bytes()[:2] == b"\xff\xd8"
    assert robot.servo_target(3) == 1500 and robot.servo_target(2) == 700
    assert [ch for ch, on in enumerate(robot.switches) if on] == [7]
    assert (robot.internal_script, robot.external_script) == (120, 272)
    await run(client, ["script", "stop", "internal"])
    await run(client, ["script", "stop", "external"])
    await run(client, ["config"])
    assert (robot.internal_script, robot.external_script) == (None, None)
    assert "sensor CH" in await run(client, ["help"])


@pytest.mark.parametrize("line, text", [
    ("", "no command"), ("bogus", "unknown command"), ("sensor x", "whole number"), ("sensor", "wrong arguments"),
    ("sensor -1", "must not be negative"), ("switch 7 maybe", "on or off"), ("script stop all", "usage"),
    ("script stop", "usage"),
    ("camera -x", "usage"), ("setconfig motor:0", "bad channel group"), ("setconfig servo:0 300", "one byte"),
    ("sleep soon", "seconds"), ("raw", "needs the bytes"),
])
async def test_bad_commands(session, line, text):
    _, client = session
    with pytest.raises(CommandError, match=text):
        await run(client, split_line(line))


async def test_unanswered_command_is_a_timeout(session):
    _, client = session
    client.timeout = 0.2
    with pytest.raises(ResponseTimeout):
        await run(client, ["sensor", "0"])  # channel 0 is a servo: the server ignores it


def test_split_keeps_raw_frames_as_typed():
    assert split_line("raw  rr1-1 --0--0-ss1\\x0c ") == ["raw", "rr1-1 --0--0-ss1\\x0c"]
    assert split_line("rr1-1--0--0-ss1\n") == ["rr1-1--0--0-ss1"]
    assert split_line("  switch 7   on ") == ["switch", "7", "on"]


def test_client_refuses_a_command_that_breaks_the_spec_unless_raw():
    """Nothing leaves for 'servo 3 99999' or 'sensor 99': the rule is named at
    once (not a timeout); --raw sends it on purpose."""
    proc, port = start_sim("-q", "--mode", "vpn")
    try:
        bad_value = run_cli("client", f"127.0.0.1:{port}", "servo 3 9999", "--timeout", "30")
        too_wide = run_cli("client", f"127.0.0.1:{port}", "servo 3 99999", "--timeout", "30")
        bad_channel = run_cli("client", f"127.0.0.1:{port}", "sensor 99", "--timeout", "30")
        sent = run_cli("client", f"127.0.0.1:{port}", "servo 3 99999", "--raw", "--timeout", "30")
    finally:
        stop(proc)
    one_line_error(bad_value, "breaks PW-RANGE-SEND-VALUE")
    one_line_error(bad_channel, "breaks PW-RANGE-CHANNEL")
    one_line_error(too_wide, "breaks PW-SYNTAX-WIDTH, PW-RANGE-SEND-VALUE")
    assert "--raw" in bad_value.stderr
    assert sent.returncode == 0 and sent.stdout == "Normal Send: channel 3 -> 99999\n"


def test_client_takes_the_password_from_the_environment():
    proc, port = start_sim("-q", "--password", "from-env")
    try:
        env_ok = run_cli("client", f"127.0.0.1:{port}", "sensor 12", env={"WHIZTAP_PASSWORD": "from-env"})
    finally:
        stop(proc)
    assert env_ok.returncode == 0 and env_ok.stdout.startswith("sensor 12 = "), env_ok.stderr
