"""Counts in what people read agree with their nouns: '1 error', '2 errors'
(``plural``, the one helper every report, verdict, meaning and command line
of the analyzer uses)."""

from __future__ import annotations

import ast
import io
import re
from collections import Counter
from pathlib import Path

from rich.console import Console

from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.analysis.report.text import headline, render_markdown, render_text
from whiztap.analyzer.analysis.verdict import verdict_of
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.examples import VPN_OPEN
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import plural
from whiztap.analyzer.traffic import Closed, Data, Opened

ROOT = Path(__file__).resolve().parent.parent
# where the analyzer's reports, verdicts, meanings and command lines and the fleet's runner are written
SPEAKING = [ROOT / "analyzer" / d for d in ("cli", "analysis", "protocol")] + [ROOT / "sniffer" / "fleet"]


def test_plural_agrees_with_its_count():
    assert [plural(n, "error") for n in (0, 1, 2)] == ["0 errors", "1 error", "2 errors"]
    assert plural(1, "entry", "entries") == "1 entry" and plural(3, "entry", "entries") == "3 entries"
    assert plural(2, "info", "info") == "2 info" and plural(12_345, "item") == "12,345 items"


def _one_error_report() -> dict:
    """One VPN connection whose client sends one Normal Send to channel 31."""
    analyzer = Analyzer("one.mcap")
    t = 1_000_000_000
    analyzer.receive(Opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000"))
    for direction, data in VPN_OPEN + [(Direction.C2S, b"rr1-31--5--0-ss1")]:
        t += 1_000_000
        analyzer.receive(Data(1, direction, t, data))
    analyzer.receive(Closed(1, t + 1_000_000, "client", "closed"))
    return build(analyzer.finish())


def test_a_report_of_one_says_one():
    """It said '1 errors', and the verdict's words had a copy of their own."""
    report = _one_error_report()
    assert headline(report).startswith("1 file, 1 connection, 3 items over ")
    words = "1 error, 1 warning, 0 info"  # the channel is out of range, and not in the configuration
    console = Console(record=True, width=200, file=io.StringIO())
    render_text(report, console)
    text = console.export_text()
    assert f"FAIL: violations at or above error ({words})" in text and "1 errors" not in text
    assert report["summary"]["violations_by_severity"] == {"error": 1, "warning": 1, "info": 0}
    assert f"**FAIL: violations at or above error ({words})**" in render_markdown(report)
    verdict = verdict_of(Counter({("PW-RANGE-CHANNEL", "client"): 1, ("PW-CHANNEL-UNCONFIGURED", "client"): 1}),
                         Counter({"PW-PAIR-UNANSWERED": 1}), 1)
    assert verdict.words() == f"{words}; 1 effect of the interventions"


def test_meanings_of_one_say_one():
    assert m.ConfigurationSettings((m.ChannelConfig(0),)).describe() == "Configuration Settings: 1 channel (1 servo)"
    assert m.SetConfiguration((m.SetConfigEntry(12, 0, 0),), 12).describe() == "Set Configuration: 1 entry, checksum 12"
    assert m.Password(b"x").describe() == "Password (1 byte)"
    assert m.CameraImage("png", b"\x89" * 2048).describe() == "Camera image (png, 2,048 bytes)"


def _strings(path: Path) -> list[tuple[int, str]]:
    """Every string and f-string of a module as written (an f-string with its expressions)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.JoinedStr):
            out.append((node.lineno, ast.unparse(node)))
        elif isinstance(node, ast.Constant) and isinstance(node.value, str):
            out.append((node.lineno, node.value))
    return out


def test_counts_are_said_one_way():
    """No '(s)' hedge and no hand-made plural ('s' * (n != 1)) where the
    analyzer speaks: a second way drifts ('1 errors' came from one)."""
    hedged = re.compile(r"""[a-z]\(s\)|['"]s['"] \* \(""")
    found = [f"{path.relative_to(ROOT)}:{n}: {text}" for folder in SPEAKING for path in folder.rglob("*.py")
             for n, text in _strings(path) if hedged.search(text)]
    assert not found
