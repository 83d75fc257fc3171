"""Hints that name a command to run next, with a path in it, are commands a
shell takes as they are: the path quoted (shlex.quote), whatever it holds
(a quote, a space, a dollar sign), and the command last on its line, after
a colon.  And the demo's replay hint names a simulator that answers as the
demo's robot did (its --seed)."""

from __future__ import annotations

import os
import shlex
from pathlib import Path

import pytest

from whiztap.analyzer.recording.output_rule import OutputRefused, check_output
from whiztap.sniffer.record.writer import RecordingFile, RecordingWriteError

from tests.cli_support import run_cli

SAMPLE = Path(__file__).resolve().parent.parent / "samples" / "clean-winsock.mcap"
NAME = "it's a $HOME `run`"  # what a shell would cut, expand or run unquoted


def command_in(text: str, *words: str) -> list[str]:
    """The command a hint ends with (after the last ': ' before it), split as a shell would."""
    start = text.index(" ".join(words))
    return shlex.split(text[start:].strip().splitlines()[0])


def cut_short(folder: Path) -> Path:
    """A recording cut in half (no footer), at a name a shell would mangle."""
    path = folder / f"{NAME}.mcap"
    data = SAMPLE.read_bytes()
    path.write_bytes(data[:len(data) // 2])
    return path


def test_the_output_rule_names_recover_for_a_part_left_by_a_crash(tmp_path):
    out = tmp_path / f"{NAME}.mcap"
    Path(f"{out}.part").write_bytes(b"left by a crash")
    with pytest.raises(OutputRefused) as refused:
        check_output(str(out), recording=True)
    assert command_in(str(refused.value), "whiztap", "recover") == ["whiztap", "recover", f"{out}.part"]


@pytest.mark.parametrize("command", ["analyze", "cat", "info", "export"])
def test_readers_name_recover_for_a_file_cut_short(tmp_path, command):
    cut = cut_short(tmp_path)
    args = ("export", cut, "--pcap", tmp_path / "x.pcapng") if command == "export" else (command, cut)
    result = run_cli(*args)
    said = result.stdout + result.stderr
    assert command_in(said, "whiztap", "recover") == ["whiztap", "recover", str(cut)], said


def test_a_write_failure_that_leaves_a_part_names_recover(tmp_path):
    file = RecordingFile(str(tmp_path / f"{NAME}.mcap"), {"session_id": "x"})
    file.open(1)
    file.write("/tcp/events", 1, b'{"event": "x"}')
    os.close(file._stream.fd)  # the disk goes away: neither the write nor the cut-back works
    with pytest.raises(RecordingWriteError) as failed:
        file.flush()
    part = f"{tmp_path / NAME}.mcap.part"
    assert command_in(str(failed.value), "whiztap", "recover") == ["whiztap", "recover", part]


@pytest.mark.slow
def test_the_demo_hints_are_shell_commands_and_its_replay_hint_seeds_the_simulator(tmp_path):
    out = tmp_path / f"{NAME}.mcap"
    result = run_cli("demo", "--headless", "--seconds", "1", "-o", out)
    assert result.returncode == 0, result.stderr
    hints = result.stdout[result.stdout.index(f"recorded {out}\n"):].splitlines()[1:]
    commands = {words[1]: words for words in map(shlex.split, hints) if len(words) > 2 and words[2] == str(out)}
    assert set(commands) == {"analyze", "cat", "tui", "replay"}, hints
    assert commands["replay"][commands["replay"].index("--password") + 1] == "progwhiz"
    sim = shlex.split(hints[-1].split("such as: ")[1])
    assert sim[1:] == ["sim", "--port", "5000", "--seed", "7"]
