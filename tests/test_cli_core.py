"""The whiztap command line as a user runs it: in this process, through the
command's own ``main``, and the installed entry point once."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol.rules import RULES
from whiztap.analyzer.protocol.text import escape
from tests.cli_support import run_cli, run_process
from tests.spec_vectors import ALL_FRAMES, HANDSHAKE_SERVER

SAMPLES = Path(__file__).parent.parent / "samples"


def test_the_installed_command_lists_the_commands():
    result = run_process("--help")
    assert result.returncode == 0
    assert "decode" in result.stdout and "rules" in result.stdout


def test_rules_json_lists_every_rule():
    result = run_cli("rules", "--format", "json")
    assert result.returncode == 0
    assert [r["id"] for r in json.loads(result.stdout)] == list(RULES)


def test_decode_clean_sample_session():
    result = run_cli("decode", str(SAMPLES / "spec-session.txt"))
    assert result.returncode == 0, result.stdout + result.stderr
    assert "Sensor value ch 8 = 512" in result.stdout
    assert result.stdout.strip().endswith("mode winsock, handshake readytogo, 0 violations")


def test_decode_reports_violations_with_exit_1():
    result = run_cli("decode", "-", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\nrr1-0--2500--0-ss1\n")
    assert result.returncode == 1
    assert "PW-RANGE-SEND-VALUE (error): Normal Send value must be 0-2000, got 2500" in result.stdout


def test_decode_reads_a_pipe_without_being_told():
    piped = run_cli("decode", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\n")
    dashed = run_cli("decode", "-", stdin="rr1-24--0--0-ss1\ns2c sr1-\\x01000-ss1\n")
    assert piped.returncode == dashed.returncode == 0, piped.stderr
    assert piped.stdout == dashed.stdout and "Fetch Configuration Settings" in piped.stdout


SESSION_RULES = {"PW-HS-ORDER", "PW-HS-COMMAND-BEFORE-READY", "PW-HS-AFTER-FAILED", "PW-VPN-CONFIG-FIRST",
                 "PW-WINSOCK-CONFIG-FIRST", "PW-UNIT-MISMATCH", "PW-CHANNEL-UNCONFIGURED", "PW-AMBIGUOUS",
                 "PW-PAIR-UNSOLICITED", "PW-PAIR-UNANSWERED", "PW-FRAME-EOL"}  # what needs what came before


def test_decode_takes_frames_as_arguments_each_judged_on_its_own():
    """A response alone was unsolicited, a command alone not the configuration
    first and never answered: rules about a session, broken by no frame."""
    vectors = [escape(raw) for raw in ALL_FRAMES + HANDSHAKE_SERVER]
    result = run_cli("decode", *vectors)
    assert result.returncode == 0, result.stdout + result.stderr
    assert "  ! " not in result.stdout
    assert result.stdout.splitlines()[-1] == f"{len(vectors)} frames, each judged on its own: 0 violations"
    assert "Servo Position Request ch 3" in result.stdout and "Response ch 2 data 100" in result.stdout
    broken = run_cli("decode", "rr1-31--0--2-ss1", "-f", "s2c cr1-3--5--0-ss1")
    assert broken.returncode == 1
    assert broken.stdout.splitlines() == [
        "c2s command    rr1-31--0--2-ss1  ->  Servo Position Request ch 31",
        "  ! PW-RANGE-CHANNEL (error): channel must be 0-23, got 31",
        "s2c response   cr1-3--5--0-ss1  ->  Response ch 3 data 5",
        "2 frames, each judged on its own: 1 violation"]


def test_decode_judges_one_line_of_a_pipe_as_a_frame_and_more_as_a_session():
    one = run_cli("decode", stdin="rr1-0--0--2-ss1\n")
    assert one.returncode == 0 and one.stdout.endswith("1 frame, each judged on its own: 0 violations\n")
    two = run_cli("decode", stdin="rr1-0--0--2-ss1\nrr1-0--0--2-ss1\n")
    assert two.returncode == 1 and "PW-VPN-CONFIG-FIRST" in two.stdout and "PW-PAIR-UNANSWERED" in two.stdout
    assert two.stdout.endswith("mode vpn, handshake none (vpn), 3 violations\n")


_frame_text = st.text(st.characters(codec="utf-8", exclude_characters="/\\\x00"), min_size=1, max_size=30)


@pytest.mark.slow
@settings(max_examples=150, deadline=None)
@given(st.lists(_frame_text.filter(lambda t: not os.path.exists(t)), min_size=1, max_size=4))
def test_decode_never_judges_a_session_on_frames_given_alone(texts):
    """Whatever is typed: one line and exit 2, or each frame judged with
    frame rules only; never a traceback."""
    result = run_cli("decode", "--", *texts)  # an unexpected error raises
    assert result.returncode in (0, 1, 2)
    assert not {rule for rule in SESSION_RULES if f"! {rule} " in result.stdout}


@pytest.mark.parametrize("args", [
    ("decode", "/nonexistent/frames.txt"),
    ("decode", "frames.txt"),
    ("decode", "samples"),
    ("decode",),
    ("decode", "-f", "rr1-24--0--0-ss1", "--checksum-rule", "crc99"),
])
def test_bad_input_is_one_line_and_exit_2(args):
    result = run_cli(*args, stdin="")  # an empty pipe: a bare 'decode' reads it and finds nothing
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
    result = run_cli(*args)
    assert (result.returncode, result.stderr) == (2, says + "\n")


def test_a_bare_whiztap_shows_the_help():
    result = run_cli()
    assert result.returncode == 2 and result.stderr.startswith("Usage: whiztap [OPTIONS] COMMAND")
    assert "Commands:" in result.stderr


def test_help_loads_no_event_loop_and_no_session_model():
    """What keeps 'whiztap --help' quick (its time is in make bench, not here):
    listing the commands imports neither asyncio nor the analyzer's session
    model, nor any UI or packet library."""
    code = ("import sys; sys.argv = ['whiztap', '--help']\n"
            "from whiztap.analyzer.cli.root import cli\n"
            "try:\n    cli()\nexcept SystemExit:\n    pass\n"
            "heavy = ('asyncio', 'whiztap.analyzer.protocol.session', 'whiztap.analyzer.analysis.analyzer', "
            "'textual', 'scapy', 'mcap')\n"
            "print(sorted(m for m in heavy if m in sys.modules), file=sys.stderr)")
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert result.returncode == 0 and "Commands:" in result.stdout, result.stderr
    assert result.stderr.strip() == "[]"
