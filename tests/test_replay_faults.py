"""Replaying a recording made under faults: none by default, the recording's
again (``--faults-from-recording``), or ones typed in (``--fault``).

Each recording is made once per module: the simulator's client through the
real recording proxy standing in the middle, the fault dropping every second
answer on channel 12.  Replays go to a fresh simulator in lockstep, so a
dropped answer is waited for (``--timeout``) and paired as the recorded client
paired it.  Under the recording's own faults the replay is judged against
what the recorded client received, and passes when it gets the same; what
the target sent before the faults is judged against what the recorded server
sent, apart.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest

from whiztap.analyzer.analysis.compare import CompareRules, Status
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.analyzer.protocol.framing import Framer, ItemKind
from whiztap.analyzer.recording.format import TOPIC_INTERVENTIONS
from whiztap.analyzer.recording.scan import RecordingScan, read_metadata
from whiztap.sniffer.record.record_run import MiddleSettings, Recording
from whiztap.sniffer.replay.engine import Replay
from whiztap.sniffer.replay.faults import recorded_faults
from whiztap.sniffer.replay.options import Pace, ReplayOptions
from whiztap.sniffer.sim.client import Client, ResponseTimeout
from whiztap.sniffer.sim.simulator import Simulator
from tests.cli_support import run_cli, run_process_async
from tests.record_support import LOCAL, closed_port, recording
from tests.replay_support import until_closed

DROP = "drop dir:s2c kind:response ch:12 every:2"
LATE = "drop dir:s2c kind:response ch:13 nth:1"
WAIT_S = "0.5"  # how long the client, and the replay, wait for an answer that may have been dropped
ROUNDS = 4  # of a Sensor Request on channel 12, then on 13: the fault drops two of the four on 12
LOCKSTEP = ("--pace", "lockstep", "--timeout", WAIT_S, "--format", "json")


def simulator() -> Simulator:
    return Simulator(port=0, mode="vpn", seed=7)


async def session(port: int, halfway: Callable[[], Awaitable[None]] | None = None) -> None:
    """ROUNDS rounds of Sensor Requests on channels 12 and 13, a dropped answer waited out."""
    async with await Client.connect(LOCAL, port) as client:
        for n in range(ROUNDS):
            if n == ROUNDS // 2 and halfway is not None:
                await halfway()
            for channel in (12, 13):
                with contextlib.suppress(ResponseTimeout):
                    await client.sensor(channel, timeout=float(WAIT_S))


async def record(path: Path, middle: MiddleSettings | None = None,
                 halfway: Callable[[Recording], Awaitable[None]] | None = None) -> None:
    """``session`` recorded through the proxy (in the middle, with ``middle``'s faults)."""
    async with simulator() as sim, recording(sim.port, path, middle=middle or MiddleSettings()) as rec:
        await session(rec.proxy.port, halfway and (lambda: halfway(rec)))
        await until_closed(sim)
        await rec.stop()


def interventions(path: Path) -> list[dict]:
    with open(path, "rb") as f:
        return [m for _topic, _t, m in RecordingScan(f, (TOPIC_INTERVENTIONS,)).messages()]


@pytest.fixture(scope="module")
def faulted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay-faults") / "faulted.mcap"
    asyncio.run(record(path, MiddleSettings(faults=(parse_fault(DROP),))))
    return path


@pytest.fixture(scope="module")
def plain(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("replay-faults") / "plain.mcap"
    asyncio.run(record(path))
    return path


async def replay_command(path: Path, *args: str) -> tuple[int, dict | str, str]:
    """``whiztap replay`` against a fresh simulator: exit status, the JSON result (or the text), stderr."""
    async with simulator() as sim:
        code, stdout, stderr = await run_process_async("replay", str(path), "--target", f"{LOCAL}:{sim.port}", *args)
    return code, json.loads(stdout) if "--format" in args else stdout, stderr


def missing(result: dict) -> list[str]:
    """The recorded answers the replay did not get, in order."""
    return [d["recorded"] for d in result["differences"] if d["status"] == "missing"]


# -- the command -------------------------------------------------------------------------------------


@pytest.mark.slow
async def test_the_recordings_faults_drop_the_same_answers_again_and_that_reproduces_it(faulted):
    dropped = [m["before"] for m in interventions(faulted) if m["action"] == "drop"]
    assert len(dropped) == ROUNDS // 2 and all(d.startswith("cr1-12--") for d in dropped)
    code, result, stderr = await replay_command(faulted, "--faults-from-recording", *LOCKSTEP)
    assert (code, stderr) == (0, "")
    assert result["faults"] == [{"name": "", "spec": DROP}] and result["fault_seed"] is None
    # the recorded client never got those answers, and neither did the replay: the same experience
    assert result["ok"] and result["differences"] == []
    assert result["answers"]["unanswered"] == len(dropped)
    assert result["answers"]["match"] == 2 * ROUNDS - len(dropped)
    # the target answered all of them, as the recorded server did
    server = result["server"]
    assert server["ok"] and server["answers"]["match"] == 2 * ROUNDS and server["differences"] == []


@pytest.mark.slow
async def test_a_replay_under_faults_that_does_not_reproduce_fails(faulted):
    """One more answer dropped than the recorded client missed: a difference."""
    code, result, _ = await replay_command(faulted, "--faults-from-recording", "--fault", LATE, *LOCKSTEP)
    assert code == 1 and not result["ok"]
    [only] = result["differences"]
    assert (only["status"], only["request"]) == ("missing", "rr1-13--0--0-ss1")
    assert result["server"]["ok"]  # the target did as the recorded server did; the extra fault did not


class _OddTarget:
    """A VPN server answering Sensor Requests like the simulator, but with a
    value out of range for the ``odd`` answers on channel 12 (by their number:
    1 is the first): what it sends there is not what the recorded server sent."""

    def __init__(self, odd: set[int]) -> None:
        self.odd = odd
        self.port = 0

    async def __aenter__(self) -> _OddTarget:
        self.server = await asyncio.start_server(self._serve, LOCAL, 0)
        self.port = self.server.sockets[0].getsockname()[1]
        return self

    async def __aexit__(self, *exc: object) -> None:
        self.server.close()
        await self.server.wait_closed()

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        framer, on_12 = Framer(), 0
        while data := await reader.read(65536):
            for item in framer.feed(data, 0):
                channel = int(item.raw.split(b"-")[1]) if item.kind is ItemKind.COMMAND else None
                if channel is None:
                    continue
                on_12 += channel == 12
                writer.write(b"cr1-%d--%d--0-ss1" % (channel, 9999 if channel == 12 and on_12 in self.odd else 7))
        writer.close()


@pytest.mark.slow
async def test_a_server_that_differs_only_where_the_faults_hide_it_is_reported_apart(faulted):
    """The target sends a wrong value exactly in the answers the recording's
    fault drops: the client's experience is the recorded one (exit 0), and the
    target's own side says where it differs from the recorded server."""
    async with _OddTarget({2, 4}) as target:
        code, stdout, stderr = await run_process_async("replay", str(faulted), "--target", f"{LOCAL}:{target.port}",
                                            "--faults-from-recording", *LOCKSTEP)
    result = json.loads(stdout)
    assert (code, stderr, result["ok"], result["answers"]["unanswered"]) == (0, "", True, ROUNDS // 2)
    server = result["server"]
    assert not server["ok"] and server["answers"]["mismatch"] == ROUNDS // 2
    assert [d["replayed"] for d in server["differences"]] == ["cr1-12--9999--0-ss1"] * (ROUNDS // 2)
    async with _OddTarget({2, 4}) as target:
        code, text, _ = await run_process_async("replay", str(faulted), "--target", f"{LOCAL}:{target.port}",
                                      "--faults-from-recording", "--pace", "lockstep", "--timeout", WAIT_S)
    assert code == 0 and "result: all answers matched" in text
    assert ("the target's own answers, before the faults, against the recorded server's: "
            f"{2 * ROUNDS - ROUNDS // 2} match, {ROUNDS // 2} mismatch") in text
    assert text.count("  MISMATCH c1 at ") == ROUNDS // 2


@pytest.mark.slow
async def test_by_default_no_fault_is_applied_and_every_answer_comes(faulted):
    code, result, stderr = await replay_command(faulted, *LOCKSTEP)
    assert (code, stderr) == (0, "")
    assert result["faults"] == [] and result["answers"]["match"] == 2 * ROUNDS and result["differences"] == []
    code, text, _ = await replay_command(faulted, "--pace", "lockstep", "--timeout", WAIT_S)
    assert code == 0 and "proxy in the middle" not in text


@pytest.mark.slow
async def test_typed_faults_apply_alone_or_after_the_recordings(faulted):
    code, result, stderr = await replay_command(faulted, "--fault", LATE, "--seed", "3", *LOCKSTEP)
    assert (code, stderr) == (1, "")
    assert result["faults"] == [{"name": "", "spec": LATE}] and result["fault_seed"] == 3
    [only] = result["differences"]  # typed faults alone: judged against what the recorded server sent
    assert (only["status"], only["request"]) == ("missing", "rr1-13--0--0-ss1")
    assert result["server"]["answers"]["match"] == 2 * ROUNDS  # the target sent it; the fault dropped it
    code, result, _ = await replay_command(faulted, "--faults-from-recording", "--fault", LATE, *LOCKSTEP)
    assert code == 1 and [f["spec"] for f in result["faults"]] == [DROP, LATE]


@pytest.mark.slow
async def test_text_output_names_the_faults(faulted):
    code, text, _ = await replay_command(faulted, "--faults-from-recording", "--pace", "lockstep",
                                         "--timeout", WAIT_S)
    assert code == 0
    assert f"through a proxy in the middle (seed none):\n  fault: {DROP}\n" in text
    assert f"{ROUNDS // 2} unanswered" in text and "MISSING" not in text
    assert "against the recorded server's: 8 match, 0 mismatch, 0 missing" in text


@pytest.mark.slow
async def test_a_recording_without_faults_is_replayed_with_a_note(plain):
    code, result, stderr = await replay_command(plain, "--faults-from-recording", *LOCKSTEP)
    assert code == 0 and result["ok"] and result["faults"] == []
    assert stderr == f"whiztap: note: {plain} was recorded without faults: there are none to re-apply\n"


@pytest.mark.parametrize(("args", "word"), [
    (("--fault", "drop bogus:1"), "'bogus:1'"),
    (("--fault", "smash dir:s2c"), "'smash'"),
    (("--fault", DROP, "--fault", "delay:soon"), "'delay:soon'"),
])
def test_a_bad_spec_is_one_line_naming_the_word(plain, args, word):
    code, stdout, stderr = run_cli("replay", plain, "--target", f"{LOCAL}:{closed_port()}", *args)
    assert code == 2 and stdout == ""
    assert stderr.startswith("whiztap: Invalid value for '--fault': ") and stderr.count("\n") == 1, stderr
    assert word in stderr and "Traceback" not in stderr


@pytest.mark.slow
async def test_seed_without_faults_and_an_unreachable_target_are_one_line(faulted):
    code, _, stderr = await run_process_async("replay", str(faulted), "--target", f"{LOCAL}:1", "--seed", "3")
    assert (code, stderr) == (2, "whiztap: --seed seeds faults: give --fault or --faults-from-recording\n")
    port = closed_port()
    code, _, stderr = await run_process_async("replay", str(faulted), "--target", f"{LOCAL}:{port}",
                                    "--faults-from-recording", "-q")
    assert code == 2 and stderr.startswith(f"whiztap: cannot connect to {LOCAL}:{port}: ") and stderr.count("\n") == 1


@pytest.mark.slow
async def test_the_output_is_recorded_through_the_faults_and_replays_under_them(faulted, tmp_path):
    out = tmp_path / "out.mcap"
    code, _, stderr = await replay_command(faulted, "--faults-from-recording", "-o", str(out), *LOCKSTEP)
    assert (code, stderr) == (0, "")
    metadata = read_metadata(str(out))
    assert (metadata["source"], metadata["middle"], json.loads(metadata["faults"])) == \
        ("replay", "yes", [{"name": "", "spec": DROP}])
    assert [m["action"] for m in interventions(out)] == ["drop"] * (ROUNDS // 2)
    # what the target sent, as whiztap record keeps it: every answer, the dropped ones too
    answers = [i.answer for c in load_exchanges(str(out)).connections for i in c.requests]
    assert len(answers) == 2 * ROUNDS and all(a is not None for a in answers)
    assert recorded_faults([out], metadata).faults == recorded_faults([faulted], read_metadata(str(faulted))).faults


# -- faults added while recording, and what is not a fault ------------------------------------------------


@pytest.mark.slow
async def test_faults_added_at_run_time_come_from_the_interventions_and_holds_do_not(tmp_path):
    path = tmp_path / "late.mcap"

    async def halfway(rec: Recording) -> None:
        rec.controller.add_fault(LATE, name="late")
        rec.controller.inject(1, "s2c", "cr1-14--5--0-ss1", force=True)

    await record(path, MiddleSettings(faults=(parse_fault(DROP),), seed=11), halfway)
    metadata = read_metadata(str(path))
    assert json.loads(metadata["faults"]) == [{"name": "", "spec": DROP}]  # only those it started with
    assert {m["action"] for m in interventions(path)} == {"drop", "inject"}
    found = recorded_faults([path], metadata)
    assert [(f.name, f.text) for f in found.faults] == [("", DROP), ("late", LATE)] and found.seed == 11
    async with simulator() as sim:
        options = ReplayOptions(target=(LOCAL, sim.port), pace=Pace.LOCKSTEP, timeout=float(WAIT_S),
                                rules=CompareRules.parse("structure"), faults=found.faults, fault_seed=found.seed)
        result = await Replay(load_exchanges(str(path)), options).run()
    assert result.counts[Status.MISSING] == ROUNDS // 2 + 1 and not result.error
    # in the replay, "late" is in force from the start: it drops the first answer on 13, not the third
    assert [d.request for d in result.differences].count(b"rr1-13--0--0-ss1") == 1

