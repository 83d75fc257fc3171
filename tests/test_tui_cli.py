"""`whiztap tui` and `whiztap demo` as a user (or CI, or make) runs them."""

import subprocess
import sys

import pytest

from whiztap.analyzer.cli.analyze import analyse_file
from tests.cli_support import run_cli
from tests.tui_support import ROOT, SAMPLES
from whiztap.tui.demo import DELIBERATE_RULES

@pytest.mark.slow
def test_the_headless_demo_prints_its_report_and_exits_0(tmp_path):
    result = run_cli("demo", "--headless", "--seconds", "2", "-o", tmp_path / "demo.mcap")
    assert result.returncode == 0, result.stderr
    out = result.stdout
    assert "whiztap conformance report" in out and "winsock" in out
    assert "failed validation" in out and "readytogo" in out
    for rule in DELIBERATE_RULES:
        assert rule in out, rule
    assert "on purpose" in out and f"whiztap analyze {tmp_path / 'demo.mcap'}" in out
    analysis = analyse_file(tmp_path / "demo.mcap", "dev-sum")
    assert set(analysis.violation_counts) == set(DELIBERATE_RULES)  # nothing but the deliberate ones
    assert analysis.frames > 50


@pytest.mark.slow
def test_the_demo_without_a_terminal_runs_headless_and_says_so(tmp_path):
    result = run_cli("demo", "--seconds", "1", cwd=tmp_path)  # stdin and stdout are not a terminal
    assert result.returncode == 0, result.stderr
    assert result.stdout.startswith("whiztap demo: no terminal, so no TUI: running headless for 1 s")
    assert (tmp_path / "demo.mcap").exists()


def test_make_demo_runs_the_demo():
    makefile = (ROOT / "Makefile").read_text()
    target = makefile[makefile.index("\ndemo:"):].split("\n\n")[0]
    assert "$(BIN)/whiztap demo" in target


@pytest.mark.parametrize("args, says", [
    ((), "give one of"),
    ((SAMPLES / "vpn.mcap", "--upstream", "127.0.0.1:5000"), "give one of"),
    (("missing.mcap",), "missing.mcap: no such file"),
    ((ROOT / "README.md",), "not an MCAP file"),
    (("--upstream", "nohost"), "--upstream must be HOST:PORT"),
    (("--follow", "gone.mcap.part"), "gone.mcap.part: cannot read"),
    ((SAMPLES / "vpn.mcap", "--checksum-rule", "nope"), "nope"),
])
def test_tui_mistakes_are_one_line_and_exit_2(args, says):
    result = run_cli("tui", *args)
    assert result.returncode == 2
    assert says in result.stderr and len(result.stderr.strip().splitlines()) == 1, result.stderr


def test_tui_without_a_terminal_says_what_to_use_instead():
    result = run_cli("tui", SAMPLES / "vpn.mcap")
    assert result.returncode == 2 and "needs a terminal" in result.stderr and "whiztap cat" in result.stderr


def test_both_commands_are_registered_and_load_no_textual():
    import click

    from whiztap.analyzer.cli.root import cli

    assert {"tui", "demo"} <= set(cli.list_commands(click.Context(cli)))
    code = "import sys, whiztap.tui.cli; sys.exit('textual' in sys.modules)"
    assert subprocess.run([sys.executable, "-c", code]).returncode == 0
