"""What a violation says to a person: its detail in words the spec uses
(never an identifier of whiztap's, such as ``client_frame``), and the spec
section it cites (the section of the message it was broken in)."""

from __future__ import annotations

import json
import re
from pathlib import Path

from hypothesis import given, settings
from hypothesis import strategies as st

from whiztap.analyzer.analysis.analyzer import Analyzer
from whiztap.analyzer.analysis.report.content import build
from whiztap.analyzer.cli.reading import scan_recording
from whiztap.analyzer.protocol.codec import decode
from whiztap.analyzer.protocol.examples import SCENARIOS, VPN_OPEN, WINSOCK_OPEN
from whiztap.analyzer.protocol.frame_text import check_frame
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction, LateViolation
from whiztap.analyzer.protocol.rules import RULES, Violation
from whiztap.analyzer.protocol.session import Session
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.cli_support import run_cli
from tests.record_support import read_all
from tests.spec_vectors import ALL_FRAMES, HANDSHAKE_SERVER

C, S = Direction.C2S, Direction.S2C
SAMPLES = Path(__file__).parent.parent / "samples"
# an identifier written the way whiztap's code names things: two words or more joined by '_'
SNAKE = re.compile(r"\b[a-z][a-z0-9]*(?:_[a-z0-9]+)+\b")
# bytes from the wire, quoted as Python shows them: what they hold is the peer's, not whiztap's words
QUOTED_BYTES = re.compile(r"""b'(?:[^'\\]|\\.)*'|b"(?:[^"\\]|\\.)*\"""")
OPENINGS = [[], VPN_OPEN, WINSOCK_OPEN, [(S, b"sendchkpass"), (C, b"pw"), (S, b"Failed Validation")],
            [(S, b"sendchkpass")]]


def _identifiers(violation: Violation) -> list[str]:
    return SNAKE.findall(QUOTED_BYTES.sub("", violation.detail))


def _session_violations(steps: list[tuple[Direction, bytes]]) -> list[Violation]:
    session = Session()
    events = []
    for t, (direction, data) in enumerate(steps, start=1):
        events += session.receive(direction, data, t * 1_000)
    events += session.close((len(steps) + 1) * 1_000)
    return [v for e in events for v in ((e.violation,) if isinstance(e, LateViolation) else e.violations)]


def _golden_steps() -> list[list[tuple[Direction, bytes]]]:
    """Every frame of the spec and every handshake word, each way, after each
    kind of opening, then every rule's scenario."""
    pieces = ALL_FRAMES + HANDSHAKE_SERVER + [b"secret\r\n", b"\r\n"]
    runs = [opening + [(direction, piece)] for opening in OPENINGS for piece in pieces for direction in (C, S)]
    return runs + list(SCENARIOS.values())


def test_no_rule_detail_names_an_identifier_on_the_spec_vectors_and_every_rule_scenario():
    """Details said ``got client_frame``, ``a set_config item``, ``after a
    None``: whiztap's names, which no reader of the spec knows."""
    seen: dict[str, set[str]] = {}
    for steps in _golden_steps():
        for v in _session_violations(steps):
            seen.setdefault(v.rule_id, set()).add(v.detail)
    for raw in ALL_FRAMES + HANDSHAKE_SERVER:
        for direction in (C, S):
            for v in check_frame(raw, direction):
                seen.setdefault(v.rule_id, set()).add(v.detail)
    assert set(seen) == set(RULES)  # every rule's details were looked at
    named = {(rule, d) for rule, details in seen.items() for d in details
             if _identifiers(Violation(rule, d))}
    assert not named


def test_no_detail_in_the_violations_samples_report_names_an_identifier():
    analyzer = Analyzer("violations.mcap")
    for event in scan_recording(SAMPLES / "violations.mcap"):
        analyzer.receive(event)
    report = build(analyzer.finish())
    assert {v["rule_id"] for v in report["violations"]} == set(RULES)
    assert not [v["detail"] for v in report["violations"] if SNAKE.findall(QUOTED_BYTES.sub("", v["detail"]))]


_piece = st.one_of(
    st.sampled_from(ALL_FRAMES + HANDSHAKE_SERVER + [b"\r\n", b"\n", b"secret"]),
    st.binary(max_size=40),
    st.text(alphabet="rcs1-_0123456789 abz\r\n", max_size=30).map(str.encode),
)


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(OPENINGS), st.lists(st.tuples(st.sampled_from([C, S]), _piece), max_size=12))
def test_no_detail_names_an_identifier_whatever_the_peers_send(opening, steps):
    for v in _session_violations(opening + steps):
        assert not _identifiers(v), (v.rule_id, v.detail)
    for _, data in steps:
        for v in check_frame(data, C) + check_frame(data, S):
            assert not _identifiers(v), (v.rule_id, v.detail)


# -- the section a violation cites ---------------------------------------------------------


def _sections(raw: bytes, rule_id: str) -> list[str]:
    kind = ItemKind.COMMAND if raw.startswith(b"rr1") else ItemKind.RESPONSE
    return [v.section for v in decode(kind, raw).violations if v.rule_id == rule_id]


def test_a_channel_out_of_range_cites_the_section_of_the_message_it_is_in():
    """The rule's own section is the Normal Send's: a Servo Position Request's
    or a response's channel was cited there too."""
    assert _sections(b"rr1-31--0--2-ss1", "PW-RANGE-CHANNEL") == ["Servo Position Request"]
    assert _sections(b"cr1-31--5--0-ss1", "PW-RANGE-CHANNEL") == ["Sensor/Servo Response"]
    assert _sections(b"rr1-31--5--0-ss1", "PW-RANGE-CHANNEL") == ["Normal Send to Channel/Port"]
    # bytes with several meanings (no channel map can choose one for channel 31): every one of them
    assert _sections(b"rr1-31--0--0-ss1", "PW-RANGE-CHANNEL") == [
        "Sensor Request, De-Activate/Open Switch or Normal Send to Channel/Port"]
    assert _sections(b"rr1-31--1--0-ss1", "PW-RANGE-CHANNEL") == [
        "Activate/Close Switch or Normal Send to Channel/Port"]


def test_a_fixed_field_cites_its_message_and_other_rules_their_own_section():
    assert _sections(b"rr1-3--9--2-ss1", "PW-FIXED-FIELD") == ["Servo Position Request"]
    assert _sections(b"cr1-3--9--4-ss1", "PW-FIXED-FIELD") == ["Sensor/Servo Response"]
    assert _sections(b"rr1-3--2500--0-ss1", "PW-RANGE-SEND-VALUE") == [RULES["PW-RANGE-SEND-VALUE"].section]


def _servo_request_out_of_range(path: Path) -> None:
    """A recording of one VPN connection whose client asks for servo 31's position."""
    recorder = Recorder(RecordingFile(str(path), {"source": "test"}))
    t = 1_000_000_000
    recorder.start(t)
    recorder.receive(Opened(1, t, "127.0.0.1:40000", "127.0.0.1:5000"))
    for direction, data in VPN_OPEN + [(C, b"rr1-31--0--2-ss1")]:
        t += 1_000_000
        recorder.receive(Data(1, direction, t, data))
    recorder.receive(Closed(1, t + 1_000_000, "client", "closed"))
    recorder.stop(t + 2_000_000)


def test_the_report_and_the_recording_cite_the_messages_section(tmp_path: Path):
    path = tmp_path / "servo.mcap"
    _servo_request_out_of_range(path)
    recorded = [m for m in read_all(str(path))["/violations"] if m["rule_id"] == "PW-RANGE-CHANNEL"]
    assert [m["section"] for m in recorded] == ["Servo Position Request"]
    done = run_cli("analyze", "--format", "json", path)
    cited = [v["section"] for v in json.loads(done.stdout)["violations"] if v["rule_id"] == "PW-RANGE-CHANNEL"]
    assert cited == ["Servo Position Request"]
    text = run_cli("analyze", path).stdout
    assert "(Servo Position Request)" in text and "Normal Send" not in text
