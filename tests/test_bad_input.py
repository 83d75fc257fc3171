"""Every command that reads a file, given every kind of bad input: one line on
stderr naming the problem, exit status 2 (3 for analyze's 'nothing to judge'),
never a traceback or 'unexpected error'."""

from __future__ import annotations

from pathlib import Path

import pytest

from tests.cli_support import run_cli
from tests.test_trust import foreign_mcap

SAMPLE = Path(__file__).parent.parent / "samples" / "clean-winsock.mcap"

# How each command is given its input; the output lands in a fresh folder.
COMMANDS = {
    "analyze": lambda f, out: ["analyze", f],
    "cat": lambda f, out: ["cat", f],
    "info": lambda f, out: ["info", f],
    "recover": lambda f, out: ["recover", f, "-o", str(out / "r.mcap")],
    "replay": lambda f, out: ["replay", f, "--target", "127.0.0.1:1", "--dry-run"],
    "stub": lambda f, out: ["stub", f, "--listen", "127.0.0.1:0", "--once"],
    "tui": lambda f, out: ["tui", f],
    "capture": lambda f, out: ["capture", "--pcap", f, "--port", "5000", "-o", str(out / "c.mcap")],
    "decode": lambda f, out: ["decode", f],
    "export-to-stdout": lambda f, out: ["analyze", f, "-o", "-", "--format", "json"],
}


# Where the input is what the command is for, or gets a verdict rather than an error.
NOT_AN_ERROR = {
    ("recover", "truncated"): 0,  # what recover is for
    ("recover", "other-tool"): 0,  # any MCAP can be copied into an indexed one
    ("info", "truncated"): 0,  # info says what the file is: truncated, and how to recover it
    ("info", "other-tool"): 0,  # ... or not written by whiztap
    ("decode", "not-mcap"): 1,  # text: judged, as garbage
}


def _inputs(tmp: Path) -> dict[str, str]:
    data = SAMPLE.read_bytes()
    files = {
        "missing": tmp / "missing.mcap",
        "empty": tmp / "empty.mcap",
        "truncated": tmp / "truncated.mcap",
        "binary": tmp / "binary.mcap",
        "directory": tmp / "folder",
        "not-mcap": tmp / "notes.mcap",
        "junk-after-magic": tmp / "junk.mcap",
        "other-tool": tmp / "other.mcap",
    }
    files["empty"].write_bytes(b"")
    files["truncated"].write_bytes(data[:len(data) // 3])
    files["binary"].write_bytes(bytes(range(256)) * 40)
    files["directory"].mkdir()
    files["not-mcap"].write_text("this is a text file, not a recording\n")
    files["junk-after-magic"].write_bytes(data[:8] + bytes(range(256)) * 8)
    foreign_mcap(files["other-tool"])
    return {k: str(v) for k, v in files.items()}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    return _inputs(tmp_path_factory.mktemp("bad"))


@pytest.mark.parametrize("kind", ["missing", "empty", "truncated", "binary", "directory", "not-mcap",
                                  "junk-after-magic", "other-tool"])
@pytest.mark.parametrize("command", sorted(COMMANDS))
def test_bad_input_is_one_line_and_exit_2(inputs, tmp_path, command, kind):
    args = COMMANDS[command](inputs[kind], tmp_path)
    result = run_cli(*args)
    assert "unexpected error" not in result.stderr and "Traceback" not in result.stderr, result.stderr
    if (command, kind) in NOT_AN_ERROR:
        assert result.returncode == NOT_AN_ERROR[command, kind], result.stderr
        return
    expected = 2
    assert result.returncode == expected, (result.returncode, result.stdout[-300:], result.stderr)
    assert result.stderr.startswith("whiztap: ") and result.stderr.count("\n") == 1, result.stderr
