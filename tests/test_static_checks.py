"""Lint and types, so that `make test` fails on either (pyproject.toml's
``[tool.ruff]`` and ``[tool.mypy]`` say what they check and why).

ruff checks the whole repository; mypy the three packages by the names they
are installed under (through the links in ``.typecheck/whiztap``), strictly for
the protocol and the traffic events.  A ``# type: ignore`` or ``# noqa`` that
remains names its code and, on the same line, why: there are few of them, and
each is a decision someone can read.
"""

from __future__ import annotations

import functools
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
BIN = Path(sys.executable).parent
CHECKED = ("analyzer", "sniffer", "tui", "tests", "benchmarks", "samples")
MAX_IGNORES = 15  # of each kind, in the whole repository

# a type-ignore comment names its codes in brackets, then after another '#' why; a noqa
# comment names its codes after a colon, then after ' - ' why
_IGNORE = re.compile(r"#\s*type:\s*ignore\b(?P<rest>.*)")
_IGNORE_WITH_REASON = re.compile(r"\[[\w-]+(?:,\s*[\w-]+)*\]\s+#\s*\S")
_NOQA = re.compile(r"#\s*noqa\b(?P<rest>.*)")
_NOQA_WITH_REASON = re.compile(r":\s*[A-Z]+\d+(?:\s*,\s*[A-Z]+\d+)*\s+-\s+\S")


def _run(*command: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(command, cwd=ROOT, capture_output=True, text=True, timeout=600)


def test_ruff_finds_nothing() -> None:
    done = _run(str(BIN / "ruff"), "check", "--output-format", "concise", ".")
    assert done.returncode == 0, done.stdout + done.stderr


@pytest.mark.timeout(600)  # a fresh clone has no cache: the first run reads every module
def test_mypy_finds_nothing() -> None:
    done = _run(str(BIN / "mypy"))
    said = done.stdout.replace(".typecheck/whiztap/", "") + done.stderr  # paths as in the repository
    assert done.returncode == 0, said
    checked = re.search(r"no issues found in (\d+) source files", said)
    assert checked is not None and int(checked[1]) > 150, said  # the packages were found, all of them


def test_the_configuration_holds_new_code_to_the_rules(tmp_path: Path) -> None:
    """What the rules ask of a new module: annotations, lines of at most 120."""
    module = tmp_path / "new_module.py"
    module.write_text(f"def f(x):\n    return {'x + ' * 40}x\n", encoding="utf-8")
    done = _run(str(BIN / "ruff"), "check", "--config", str(ROOT / "pyproject.toml"), "--no-cache",
                "--output-format", "concise", str(module))
    assert {"ANN001", "ANN201", "E501"} <= set(re.findall(r"\b([A-Z]+\d+)\b", done.stdout)), done.stdout


@functools.cache
def _all_comments() -> list[tuple[str, str]]:
    """(where, text) of every comment in the checked folders: comments only,
    as Python reads them, never text in a string."""
    found = []
    for top in CHECKED:
        for path in sorted((ROOT / top).rglob("*.py")):
            with path.open("rb") as f:
                found += [(f"{path.relative_to(ROOT)}:{token.start[0]}", token.string)
                          for token in tokenize.tokenize(f.readline) if token.type == tokenize.COMMENT]
    return found


def _comments(pattern: re.Pattern[str]) -> list[tuple[str, str]]:
    """(where, what follows the marker) of each comment ``pattern`` finds."""
    return [(where, m["rest"]) for where, text in _all_comments() if (m := pattern.search(text)) is not None]


@pytest.mark.parametrize(("kind", "pattern", "with_reason"), [
    ("type: ignore", _IGNORE, _IGNORE_WITH_REASON),
    ("noqa", _NOQA, _NOQA_WITH_REASON),
], ids=["type-ignore", "noqa"])
def test_each_ignore_names_its_code_and_why(kind: str, pattern: re.Pattern[str],
                                             with_reason: re.Pattern[str]) -> None:
    found = _comments(pattern)
    unexplained = [where for where, rest in found if not with_reason.match(rest)]
    assert unexplained == [], f"a {kind} without its code and reason on the line"
    assert len(found) <= MAX_IGNORES, f"{len(found)} {kind} comments: fix the code rather than silence it"
