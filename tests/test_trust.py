"""Verdicts on ordinary malformed traffic, recorded through the real proxy: every
command that judges a recording gives the same verdict, and none crashes."""

from __future__ import annotations

import json
import subprocess

import pytest

from tests.record_support import WHIZTAP, record_dialogue

CONFIG = b"sr1-\x18" + b"200" * 24 + b"-ss1"  # 24 sensors


def run(*args: object) -> subprocess.CompletedProcess:
    return subprocess.run([WHIZTAP, *map(str, args)], capture_output=True, text=True, timeout=120)


def judged(path) -> tuple[dict, list[dict]]:
    """The report and cat's items; neither may crash."""
    report = run("analyze", path, "--format", "json")
    assert report.returncode in (0, 1), report.stderr
    items = run("cat", path, "--format", "jsonl")
    assert items.returncode == 0, items.stderr
    assert "unexpected error" not in report.stderr + items.stderr
    return json.loads(report.stdout), [json.loads(line) for line in items.stdout.splitlines()]


@pytest.mark.parametrize("answer", [b"cr1-12-ss1", b"cr1--ss1", b"cr1-12--\xff\xfe--0-ss1", b"cr1-12--1x0--0-ss1"])
async def test_an_answer_that_does_not_parse_is_judged_not_a_crash(tmp_path, answer):
    path = await record_dialogue(
        tmp_path / "r.mcap",
        [("recv", 16), ("send", CONFIG), ("recv", 16), ("send", answer)],
        [("send", b"rr1-24--0--0-ss1"), ("recv", len(CONFIG)), ("send", b"rr1-12--0--0-ss1"),
         ("recv", len(answer))])
    report, items = judged(path)
    assert not report["passed"]
    assert any(line["kind"] == "response" and line["violations"] for line in items)
    live = run("decode", "-f", answer.decode("latin-1").encode("unicode_escape").decode())
    assert live.returncode == 1 and "unexpected error" not in live.stderr


async def test_a_login_abandoned_mid_password_is_judged_not_a_crash(tmp_path):
    """Recorded with the default redaction: the password bytes are masked."""
    path = await record_dialogue(
        tmp_path / "r.mcap", [("send", b"sendchkpass\r\n"), ("recv", 4)],
        [("recv", 13), ("send", b"prog"), ("eof",), ("sleep", 0.1)])
    report, items = judged(path)
    [conn] = report["connections"]
    assert conn["mode"] == "winsock"
    assert b"prog" not in json.dumps(items).encode()
