"""The whiztap command line as a user runs it: a real subprocess."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from whiztap.analyzer.protocol.rules import RULES

WHIZTAP = str(Path(sys.executable).with_name("whiztap"))
SAMPLES = Path(__file__).parent.parent / "samples"


def run(*args, stdin=None):
    return subprocess.run([WHIZTAP, *args], capture_output=True, text=True, input=stdin, timeout=60)


def test_help_lists_the_commands():
    result = run("--help")
    assert result.returncode == 0
    assert "decode" in result.stdout and "rules" in result.stdout


def test_rules_json_lists_every_rule():
    result = run("rules", "--format", "json")
    assert result.returncode == 0
    assert [r["id"] for r in json.loads(result.stdout)] == list(RULES)


def test_decode_clean_sample_session():
    result = run("decode", str(SAMPLES / "spec-session.txt"))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Sensor value ch 8 = 512" in result.stdout
    assert result.stdout.strip().endswith("mode winsock, handshake readytogo, 0 violation(s)")


def test_decode_reports_violations_with_exit_1():
    result = run("decode", "-", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\nrr1-0--2500--0-ss1\n")
    assert result.returncode == 1
    assert "PW-RANGE-SEND-VALUE (error): Normal Send value must be 0-2000, got 2500" in result.stdout


def test_decode_reads_a_pipe_without_being_told():
    piped = run("decode", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\n")
    dashed = run("decode", "-", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\n")
    assert piped.returncode == dashed.returncode == 0, piped.stderr
    assert piped.stdout == dashed.stdout and "Fetch Configuration Settings" in piped.stdout


@pytest.mark.parametrize("args", [
    ("decode", "/nonexistent/frames.txt"),
    ("decode",),
    ("decode", "-f", "rr1-24--0--0-ss1", "--checksum-rule", "crc99"),
])
def test_bad_input_is_one_line_and_exit_2(args):
    result = run(*args, stdin="")  # an empty pipe: a bare 'decode' reads it and finds nothing
    assert result.returncode == 2
    assert result.stderr.startswith("whiztap: ")
    assert len(result.stderr.strip().splitlines()) == 1
    assert "Traceback" not in result.stderr


@pytest.mark.parametrize("args, says", [
    (("frobnicate",), "whiztap: No such command 'frobnicate'. (see 'whiztap --help')"),
    (("rules", "--nope"), "whiztap: No such option '--nope'. (see 'whiztap rules --help')"),
    (("cat",), "whiztap: Missing argument 'RECORDING'. (see 'whiztap cat --help')"),
    (("info", "samples"), "whiztap: samples: names 5 recordings (samples/clean-winsock.mcap, "
                          "samples/failed-password.mcap, ...); give one (a split recording's parts count as one) "
                          "(see 'whiztap info --help')"),
])
def test_usage_errors_are_one_line_that_names_the_help(args, says):
    result = run(*args)
    assert (result.returncode, result.stderr) == (2, says + "\n")


def test_a_bare_whiztap_shows_the_help():
    result = run()
    assert result.returncode == 2 and result.stderr.startswith("Usage: whiztap [OPTIONS] COMMAND")
    assert "Commands:" in result.stderr


def test_help_loads_no_event_loop_and_no_session_model():
    """What keeps 'whiztap --help' quick (its time is in make bench, not here):
    listing the commands imports neither asyncio nor the analyzer's session
    model, nor any UI or packet library."""
    code = ("import sys; sys.argv = ['whiztap', '--help']\n"
            "from whiztap.analyzer.cli.root import cli\n"
            "try:\n    cli()\nexcept SystemExit:\n    pass\n"
            "heavy = ('asyncio', 'whiztap.analyzer.protocol.session', 'whiztap.analyzer.analysis.analyzer', 'textual', 'scapy', 'mcap')\n"
            "print(sorted(m for m in heavy if m in sys.modules), file=sys.stderr)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "Commands:" in result.stdout, result.stderr
    assert result.stderr.strip() == "[]"
