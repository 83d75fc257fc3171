"""A fault says what it will do, and says so when it does nothing (issue 26, item 4).

``record``, ``tui`` and ``demo`` print each fault in words at start; a fault
that chose no frame while its direction carried ``QUIET_AFTER`` frames is
named then, and again when the proxy stops, on stderr (or the TUI's notices),
in the closing summary and on the recording's /log; every fault's dict counts
the frames it ``matched``.  At most ``MAX_FAULTS`` are in force, whichever way
they come; a frame is offered only to the faults that may choose its
direction and kind.  The grammar's own errors are in ``test_fault_spec.py``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from whiztap.analyzer.mitm.faults import MAX_FAULTS, Fault
from whiztap.analyzer.mitm.quiet import QUIET_AFTER
from whiztap.analyzer.protocol import messages as m
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.mitm.controller import ControlError, Controller
from whiztap.sniffer.record.summary import summary_lines
from tests.cli_support import Ran, run_cli
from tests.core_support import S, FakeClockMiddle
from tests.middle_support import Raw, middle, sensor
from tests.record_support import LOCAL, RecordProcess, closed_port

C2S, S2C = Direction.C2S, Direction.S2C


def answers(n: int, channel: int = 12) -> bytes:
    return b"".join(encode(m.ChannelResponse(channel, i % 1000)) for i in range(n))


def logged(mid: FakeClockMiddle) -> list[tuple[str, str]]:
    """What the controller gave the recording's /log, as (name, line)."""
    lines: list[tuple[str, str]] = []
    mid.controller.log = lambda name, line, t_ns: lines.append((name, line))
    return lines


# -- only the faults that may choose a frame are asked ------------------------------------------------------


def test_a_frame_is_offered_only_to_the_faults_of_its_direction_and_kind(monkeypatch):
    offered: list[int] = []
    real = Fault.frame
    monkeypatch.setattr(Fault, "frame", lambda self, frame: (offered.append(self.id), real(self, frame))[1])
    mid = FakeClockMiddle(*["drop dir:c2s"] * 200, "drop dir:s2c kind:image", "delay:0ms dir:s2c ch:99",
                          "drop kind:response ch:99")
    mid.send(S2C, answers(10))
    assert sorted(set(offered)) == [202, 203] and len(offered) == 20  # not the 200 on c2s, nor the image one
    assert mid.got(S2C) == answers(10)


def test_the_faults_a_frame_is_offered_to_keep_their_order():
    # replace, then a fault of the other direction, then corrupt: the corrupt sees the replacement
    mid = FakeClockMiddle("replace:'cr1-12--1--0-ss1' dir:s2c nth:1", "drop dir:c2s", "corrupt dir:s2c nth:1")
    mid.send(S2C, answers(1))
    assert mid.got(S2C) == b"cr1-13--1--0-ss1"


def test_switching_a_fault_off_and_on_and_removing_it_changes_what_it_is_offered():
    mid = FakeClockMiddle("drop dir:s2c ch:12")
    mid.send(S2C, answers(2))
    mid.controller.enable_fault(1, False)
    mid.send(S2C, answers(3))
    mid.controller.enable_fault(1, True)
    mid.send(S2C, answers(1))
    assert mid.controller.fault(1).as_dict()["matched"] == 3 and mid.got(S2C) == answers(3)
    mid.controller.remove_fault(1)
    mid.send(S2C, answers(1))
    assert mid.got(S2C) == answers(3) + answers(1)


# -- matched, and faults that choose nothing ------------------------------------------------------------------


def test_a_fault_counts_the_frames_it_chose_beside_those_it_acted_on():
    mid = FakeClockMiddle("drop dir:s2c kind:response ch:12 every:2")
    mid.send(S2C, answers(4) + answers(3, channel=13))
    listed = mid.controller.state()["faults"][0]
    assert (listed["matched"], listed["hits"]) == (4, 2)
    assert listed["meaning"] == "drop, s2c, every 2nd frame of kind response on channel 12 of each connection"


def test_a_fault_that_chose_none_of_a_thousand_frames_of_its_direction_is_named_once():
    mid = FakeClockMiddle("drop dir:s2c ch:99", "drop dir:s2c ch:12 nth:100000", "drop ch:99", "drop dir:c2s")
    logs = logged(mid)
    mid.send(S2C, answers(QUIET_AFTER - 1))
    assert mid.reports == [] and logs == []
    mid.send(S2C, answers(1))
    assert mid.reports == [
        "warning: fault fault-1 (drop dir:s2c ch:99) chose none of the 1,000 s2c frames since it was put in "
        "force; is its SPEC what you meant?",
        "warning: fault fault-3 (drop ch:99) chose none of the 1,000 frames since it was put in force; "
        "is its SPEC what you meant?"]
    assert logs == [(name, line.removeprefix("warning: ")) for name, line in
                    zip(("fault-1", "fault-3"), mid.reports)]
    mid.send(S2C, answers(500))
    assert len(mid.reports) == 2  # once; fault-2 chose frames, fault-4 saw none of its direction


def test_at_the_end_every_fault_in_force_that_chose_nothing_is_named_again():
    mid = FakeClockMiddle("drop dir:s2c ch:99", "drop dir:s2c ch:12", "drop dir:c2s", "drop ch:98")
    mid.controller.enable_fault(4, False)  # off: not in force
    logs = logged(mid)
    mid.send(S2C, answers(5))
    quiet = mid.controller.end()
    assert [f.name for f in quiet] == ["fault-1"]
    assert mid.reports == ["warning: fault fault-1 (drop dir:s2c ch:99) chose none of the 5 s2c frames it saw"]
    assert logs == [("fault-1", "fault fault-1 (drop dir:s2c ch:99) chose none of the 5 s2c frames it saw")]
    mid.send(S2C, answers(1))
    assert [f.name for f in mid.controller.end()] == ["fault-1"]
    assert mid.reports[-1].endswith("chose none of the 6 s2c frames it saw")


def test_a_fault_counts_from_when_it_was_put_in_force():
    mid = FakeClockMiddle()
    mid.send(S2C, answers(QUIET_AFTER))
    mid.controller.add_fault("drop dir:s2c ch:99")
    mid.send(S2C, answers(QUIET_AFTER - 1))
    assert mid.reports == []
    mid.controller.enable_fault(1, False)
    mid.controller.enable_fault(1, True)  # on again: it counts anew
    mid.send(S2C, answers(QUIET_AFTER - 1))
    assert mid.reports == []
    mid.send(S2C, answers(1))
    assert len(mid.reports) == 1 and "1,000 s2c frames" in mid.reports[0]


def test_a_fault_that_acted_on_a_timer_is_not_quiet():
    mid = FakeClockMiddle("reset dir:s2c kind:image after:1s", "drop dir:s2c kind:image")
    mid.send(S2C, answers(3))
    mid.advance(2 * S)
    assert [f.name for f in mid.controller.end()] == ["fault-2"]


@pytest.mark.slow
async def test_a_quiet_fault_is_named_on_stderr_in_the_summary_and_on_log(tmp_path):
    async with middle(tmp_path / "r.mcap", "drop dir:s2c ch:99", "drop dir:s2c ch:12 nth:1") as mid:
        raw = await Raw.open(mid.port)
        await raw.send(*[sensor(12)] * (QUIET_AFTER + 1))
        await raw.nothing_more(QUIET_AFTER)  # the first answer dropped
        await raw.close()
        await mid.rec.stop()
    said = "fault fault-1 (drop dir:s2c ch:99) chose none of the"
    assert mid.warnings == [f"warning: {said} 1,000 s2c frames since it was put in force; is its SPEC what you "
                            f"meant?", f"warning: {said} 1,001 s2c frames it saw"]
    summary = mid.rec.summary
    assert summary["quiet_faults"] == ["fault-1 (drop dir:s2c ch:99)"]
    assert summary_lines(summary, "recorded")[-1] == "  faults that chose no frame: fault-1 (drop dir:s2c ch:99)"
    logs = [log for log in mid.topics()["/log"] if log["file"] == "whiztap"]  # the others are violations
    assert [(log["name"], log["message"], log["level"], log["line"]) for log in logs] == [
        ("fault-1", line.removeprefix("warning: "), 3, 0) for line in mid.warnings]


# -- at most MAX_FAULTS, whichever way they come ----------------------------------------------------------------


def test_the_api_refuses_one_fault_too_many_in_one_line():
    controller = Controller()
    for i in range(MAX_FAULTS):
        controller.add_fault(f"drop ch:{i}")
    with pytest.raises(ControlError) as caught:
        controller.add_fault("drop")
    assert caught.value.status == 400 and str(caught.value).startswith(f"{MAX_FAULTS} faults are in force")


def _record(*args: str) -> Ran:
    return run_cli("record", "--listen", "127.0.0.1:0", "--upstream", f"{LOCAL}:{closed_port()}", *args)


def _one_line(result: Ran, *words: str) -> None:
    assert result.returncode == 2, result.stderr
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("whiztap: "), result.stderr
    assert "unexpected error" not in result.stderr
    for word in words:
        assert word in result.stderr


def test_record_refuses_one_fault_too_many_in_one_line(tmp_path):
    out = tmp_path / "r.mcap"
    _one_line(_record("-o", str(out), *["--fault", "drop"] * (MAX_FAULTS + 1)),
              f"{MAX_FAULTS + 1} faults given (--faults and --fault); at most {MAX_FAULTS}")
    faults = tmp_path / "faults.toml"
    faults.write_text("".join(f'[faults.f{i}]\nspec = "drop ch:{i}"\n' for i in range(MAX_FAULTS)))
    _one_line(_record("-o", str(out), "--faults", str(faults), "--fault", "drop"), f"{MAX_FAULTS + 1} faults given")
    assert not out.exists()


def test_a_fault_file_nested_thousands_deep_is_one_line_for_each_command(tmp_path):
    deep = tmp_path / "deep.toml"
    deep.write_text("[faults.x]\nspec = " + "[" * 5000 + "]" * 5000 + "\n")
    words = (str(deep), "nested too deeply")
    _one_line(_record("-o", str(tmp_path / "r.mcap"), "--faults", str(deep)), *words)
    _one_line(run_cli("tui", "--upstream", f"{LOCAL}:9", "-o", tmp_path / "t.mcap", "--faults", deep), *words)
    _one_line(run_cli("demo", "--headless", "-o", tmp_path / "d.mcap", "--faults", deep), *words)
    assert not list(tmp_path.glob("*.mcap*"))


# -- each fault in words at start ------------------------------------------------------------------------------


FAULT_ARGS = ("--fault", "delay:200ms dir:s2c", "--fault", "drop dir:s2c kind:response ch:12 every:2")
FAULT_LINES = ["fault-1: delay 200 ms, s2c, all frames",
               "fault-2: drop, s2c, every 2nd frame of kind response on channel 12 of each connection"]


@pytest.mark.slow
@pytest.mark.parametrize("quiet", [False, True], ids=["plain", "-q"])
async def test_record_prints_each_fault_in_words_at_start_unless_quiet(tmp_path, quiet):
    faults = tmp_path / "faults.toml"
    faults.write_text('[faults.slow]\nspec = "delay:1s dir:c2s kind:command"\n')
    rec = await RecordProcess.start(closed_port(), tmp_path / "r.mcap", "--faults", str(faults), *FAULT_ARGS,
                                    *(["-q"] if quiet else []))
    status, _, err = await rec.finish()
    assert status == 0
    started = ["slow: delay 1 s, c2s, all frames of kind command",  # a named fault is fault 1 all the same
               "fault-2: delay 200 ms, s2c, all frames",
               "fault-3: drop, s2c, every 2nd frame of kind response on channel 12 of each connection"]
    said = [line for line in err.splitlines() if line.startswith(("slow:", "fault-"))]  # beside the upstream's warning
    assert said == ([] if quiet else started)


def test_tui_prints_each_fault_in_words_before_the_app_starts(tmp_path):
    result = run_cli("tui", "--upstream", f"{LOCAL}:9", "-o", tmp_path / "t.mcap", *FAULT_ARGS)
    # without a terminal the app itself does not start; the faults were said first
    assert result.stderr.splitlines()[:2] == FAULT_LINES and "needs a terminal" in result.stderr


@pytest.mark.slow
def test_demo_prints_each_fault_in_words_at_start(tmp_path):
    result = run_cli("demo", "--headless", "--seconds", "0.2", "-o", tmp_path / "d.mcap", *FAULT_ARGS)
    assert result.returncode == 0, result.stderr
    assert result.stderr.splitlines()[:2] == FAULT_LINES
    assert Path(tmp_path / "d.mcap").exists()
