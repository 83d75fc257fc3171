"""A request the server still owed when the proxy reset or closed the
connection is the end's effect, not the server's violation (the server had no
chance to answer): one verdict for what the proxy did (issue 25, item 7)."""

from __future__ import annotations

import pytest

from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.analysis.report.content import build
from tests.middle_drive import C2S, MS, S2C, Drive

FETCH = b"rr1-24--0--0-ss1"
CONFIG = b"sr1-\x01100-ss1"


def _report(drive: Drive) -> dict:
    analyzer = Analyzer("drive", every_event=False, middle=True)
    for event in drive.events:
        analyzer.receive(event)
    return build(analyzer.finish())


@pytest.mark.parametrize("spec", ["reset after:100ms", "close after:100ms"])
def test_a_request_cut_off_by_the_proxys_end_is_its_effect(spec):
    drive = Drive()
    drive.api("POST", "/faults", {"spec": spec})
    drive.open(1)
    drive.send(1, C2S, FETCH)
    drive.send(1, S2C, CONFIG)  # answered
    drive.send(1, C2S, b"rr1-0--0--2-ss1")  # a Servo Position Request the server has not answered yet
    drive.advance(200 * MS)  # the proxy ends the connection
    report = _report(drive)
    assert not [v for v in report["violations"] if v["rule_id"] == "PW-PAIR-UNANSWERED"], report["violations"]
    effects = report["interventions"]["effects"]
    assert [(e["rule_id"], e["cause"]) for e in effects] == [("PW-PAIR-UNANSWERED", f"fault fault-1: {spec}")]


def test_a_request_unanswered_before_the_proxys_end_is_still_the_servers():
    drive = Drive()
    drive.api("POST", "/faults", {"spec": "reset after:7s"})
    drive.open(1)
    drive.send(1, C2S, FETCH)
    drive.send(1, S2C, CONFIG)
    drive.send(1, C2S, b"rr1-0--0--2-ss1")
    drive.advance(6000 * MS)
    drive.send(1, C2S, FETCH)  # traffic after its 5 s deadline: the session sees it pass, the server's own
    drive.send(1, S2C, CONFIG)
    drive.advance(2000 * MS)  # then the proxy resets the connection
    report = _report(drive)
    assert [v["side"] for v in report["violations"] if v["rule_id"] == "PW-PAIR-UNANSWERED"] == ["server"]
