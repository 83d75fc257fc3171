"""Replaying a recorded client against the real simulator, in-process and as ``whiztap replay``.

The recording is made once per module: the client library through the real
recording proxy against a frozen-clock simulator (tests/replay_support.py).
"""

from __future__ import annotations

import asyncio
import json
import os
import re
import signal

import pytest

from whiztap.analyzer.analysis.compare import CompareRules, Status
from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.sniffer.sim.faults import FaultConfig
from whiztap.sniffer.replay.engine import Replay
from whiztap.sniffer.replay.events import ConnectionClosed, ConnectionOpened, Finished, RequestSent, ResponseCompared
from whiztap.sniffer.replay.options import Pace, ReplayError, ReplayOptions
from whiztap.sniffer.replay.plan import Selection, kinds_of, plan
from whiztap.sniffer.sim.client import Client, HandshakeError
from tests.record_support import LOCAL, WAIT, both_ways, closed_port, recording
from tests.cli_support import run_cli, run_process_async, start_process
from tests.replay_support import PASSWORD, record, simulator, until_closed

EXACT = CompareRules.parse("exact")
STRUCTURE = CompareRules.parse("structure")


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    path = tmp_path_factory.mktemp("replay") / "session.mcap"
    asyncio.run(record(path, seed=1))
    return path


@pytest.fixture(scope="module")
def exchanges(recorded):
    return load_exchanges(str(recorded))


def options(port: int, **kw) -> ReplayOptions:
    kw.setdefault("pace", Pace.MAX)
    kw.setdefault("rules", EXACT)
    kw.setdefault("timeout", 1.0)
    kw.setdefault("password", PASSWORD.encode())
    return ReplayOptions(target=(LOCAL, port), **kw)


def answers(exchanges) -> int:
    return sum(1 for c in exchanges.connections for i in c.items if i.answer is not None)


async def replay(exchanges, opts: ReplayOptions, events: list | None = None):
    return await Replay(exchanges, opts, on_event=events.append if events is not None else None).run()


# -- against the simulator ---------------------------------------------------------------------


@pytest.mark.slow
async def test_same_seed_matches_exactly_and_the_output_is_a_recording_of_the_same_bytes(exchanges, recorded,
                                                                                        tmp_path):
    out = tmp_path / "replayed.mcap"
    events: list = []
    async with simulator(seed=1) as sim:
        result = await replay(exchanges, options(sim.port, output=str(out)), events)
    assert result.ok and result.exit_status == 0, [d.diff for d in result.differences]
    handshake = len(exchanges.connections[0].handshake)
    assert result.counts[Status.MATCH] == answers(exchanges) + handshake
    assert [type(e) for e in (events[0], events[-2], events[-1])] == [ConnectionOpened, ConnectionClosed, Finished]
    compared = [e for e in events if isinstance(e, ResponseCompared)]
    assert all(e.match and e.recorded == e.replayed and e.diff == "" for e in compared)
    # the replayed session, recorded: the server said exactly what it said before
    original, replayed = both_ways(str(recorded)), both_ways(str(out))
    assert replayed[(1, "s2c")] == original[(1, "s2c")]
    assert replayed[(1, "c2s")] == original[(1, "c2s")]  # the password is redacted in both
    async with simulator(seed=1) as sim:  # and it is replayable in turn
        again = await replay(load_exchanges(str(out)), options(sim.port))
    assert again.ok and again.counts[Status.MATCH] == result.counts[Status.MATCH]


async def test_another_seed_matches_in_structure_but_not_exactly(exchanges):
    async with simulator(seed=2) as sim:  # a fresh robot for each: camera frames count up
        structural = await replay(exchanges, options(sim.port, rules=STRUCTURE))
    async with simulator(seed=2) as sim:
        exact = await replay(exchanges, options(sim.port, rules=EXACT))
    assert structural.ok, [d.diff for d in structural.differences]
    assert exact.exit_status == 1
    assert {d.status for d in exact.differences} == {Status.MISMATCH}
    sensor_diffs = [d for d in exact.differences if d.request_text.startswith("Sensor Request")]
    assert sensor_diffs and len(sensor_diffs) == len(exact.differences)  # only the readings differ
    for d in sensor_diffs:
        assert "sensor_value: " in d.diff and d.recorded != d.replayed
        recorded_value = d.recorded.split(b"--")[1].decode()
        replayed_value = d.replayed.split(b"--")[1].decode()
        assert f"sensor_value: {recorded_value}" in d.diff and f"sensor_value: {replayed_value}" in d.diff
        assert d.diff.startswith(f"MISMATCH c1 at {d.recorded_s:.6f} s after rr1-")


@pytest.mark.slow
async def test_lockstep_reports_each_dropped_answer_as_missing(exchanges):
    faults = FaultConfig(latency_ms=20, drop_rate=0.5)
    async with simulator(seed=1, faults=faults) as sim:
        result = await replay(exchanges, options(sim.port, pace=Pace.LOCKSTEP, rules=STRUCTURE, timeout=0.4))
        dropped = sim.stats.answers_dropped
    missing = [d for d in result.differences if d.status is Status.MISSING]
    assert dropped > 0 and len(missing) == dropped
    assert all(d.replayed is None and d.recorded is not None and "(no answer)" in d.diff for d in missing)
    assert result.counts[Status.MATCH] == answers(exchanges) + 2 - dropped  # + the handshake
    assert result.exit_status == 1


async def test_recorded_pacing_keeps_writing_on_schedule_and_reports_its_drift(exchanges):
    faults = FaultConfig(latency_ms=20, drop_rate=0.5)
    sent: list = []
    async with simulator(seed=1, faults=faults) as sim:
        result = await replay(exchanges, options(sim.port, pace=Pace.RECORDED, rules=STRUCTURE, timeout=0.4,
                                                 rate=1.0), sent)
    writes = [e for e in sent if isinstance(e, RequestSent)]
    planned = sum(len(p.sends) for p in plan(exchanges, Selection(), False)) + 1  # + the password
    assert len(writes) == result.writes == planned  # no write waited for a dropped answer
    assert all(e.drift_ns is not None and e.drift_ns >= 0 for e in writes)
    drift = result.drift
    assert drift is not None and drift.count == planned
    assert 0 <= drift.p50_ns <= drift.p99_ns <= drift.max_ns == max(e.drift_ns for e in writes)
    assert re.fullmatch(r"drift from schedule over \d+ writes: p50 \d+\.\d{3} ms, p99 \d+\.\d{3} ms, "
                        r"max \d+\.\d{3} ms \(schedule moved up to \d+\.\d{3} ms later by the server's "
                        r"handshake\)", drift.text())
    # the simulator holds every handshake line 20 ms, which the recording never waited:
    # the writes after it keep their recorded gaps from it instead of all leaving late
    assert drift.shift_ns >= 20_000_000 / 2
    assert any(d.status is Status.MISSING for d in result.differences)


def test_the_schedule_divides_recorded_gaps_by_the_rate():
    from whiztap.sniffer.replay.pacing import Pacer

    pacer = Pacer(rate=2.0)
    pacer.anchor(1_000_000_000)
    assert pacer.due(1_010_000_000) - pacer.due(1_000_000_000) == 5_000_000  # 10 ms recorded, at 2x
    assert pacer.late_by(10**18) == 0  # not due for decades: not late


async def test_exact_segments_resend_the_recorded_reads(exchanges, tmp_path):
    out = tmp_path / "segments.mcap"
    async with simulator(seed=1) as sim:
        result = await replay(exchanges, options(sim.port, segments=True, output=str(out)))
    assert result.ok, [d.diff for d in result.differences]
    original = [r.data for r in exchanges.connections[0].reads if b"*" not in r.data]
    replayed = [r.data for r in load_exchanges(str(out)).connections[0].reads if b"*" not in r.data]
    assert replayed == original


async def test_a_line_break_after_the_password_is_sent_with_it(tmp_path):
    async def crlf_client(port: int) -> list:
        reader, writer = await asyncio.open_connection(LOCAL, port)
        assert await reader.readexactly(11) == b"sendchkpass"
        writer.write(PASSWORD.encode() + b"\r\n")
        assert await reader.readexactly(9) == b"readytogo"
        writer.write(b"rr1-24--0--0-ss1")
        got = await reader.readuntil(b"-ss1")
        writer.close()
        return [got]

    path, out = tmp_path / "crlf.mcap", tmp_path / "crlf-replayed.mcap"
    await record(path, session=crlf_client)
    recording = load_exchanges(str(path))
    [p] = plan(recording, Selection(), False)
    assert p.password_tail == b"\r\n" and [s.data for s in p.sends] == [b"rr1-24--0--0-ss1"]
    async with simulator(seed=1) as sim:
        result = await replay(recording, options(sim.port, output=str(out)))
    assert result.ok, [d.diff for d in result.differences]
    assert both_ways(str(out))[(1, "c2s")] == both_ways(str(path))[(1, "c2s")]  # the redacted password and CRLF


@pytest.mark.parametrize("keep_secrets", [False, True])
async def test_a_refused_password_is_replayed_refused(tmp_path, keep_secrets):
    async def refused_then_accepted(port: int) -> list:
        with pytest.raises(HandshakeError):
            await Client.connect(LOCAL, port, password="not-" + PASSWORD)
        async with await Client.connect(LOCAL, port, password=PASSWORD) as client:
            return [await client.sensor(12)]

    path = tmp_path / "refused.mcap"
    async with simulator(seed=1) as sim, recording(sim.port, path, keep_secrets=keep_secrets) as rec:
        await refused_then_accepted(rec.proxy.port)
        await until_closed(sim)
        await rec.stop()
    recorded = load_exchanges(str(path))
    assert [c.refused for c in recorded.connections] == [True, False]
    # kept secrets: each connection sends the password it recorded, no --password needed
    events: list = []
    async with simulator(seed=1) as sim:
        opts = options(sim.port, password=None) if keep_secrets else options(sim.port)
        result = await replay(recorded, opts, events)
    assert result.ok, [d.diff for d in result.differences]
    verdicts = [(e.conn, e.replayed, e.status) for e in events
                if isinstance(e, ResponseCompared) and e.request_text == "the password"]
    assert verdicts == [(1, b"Failed Validation", Status.MATCH), (2, b"readytogo", Status.MATCH)]


async def test_loop_filters_and_connection_choice(exchanges):
    sent: list = []
    async with simulator(seed=1) as sim:
        result = await replay(exchanges, options(sim.port, loop=2, selection=Selection(
            conns=frozenset({1}), kinds=frozenset({"sensor"}))), sent)
    assert result.ok and result.connections == 2
    texts = [e.text for e in sent if isinstance(e, RequestSent) and e.text != "Password"]
    assert len(texts) == 2 * 6 and all(t.startswith("Sensor Request ch ") for t in texts)
    async with simulator(seed=1) as sim:
        with pytest.raises(ReplayError, match="no connection is selected"):
            await replay(exchanges, options(sim.port, selection=Selection(conns=frozenset({9}))))


async def test_pause_step_resume(exchanges):
    sent: list = []
    async with simulator(seed=1) as sim:
        r = Replay(exchanges, options(sim.port, pace=Pace.LOCKSTEP), on_event=sent.append)
        r.pause()
        task = asyncio.create_task(r.run())
        await asyncio.sleep(0.2)
        def writes():
            return [e for e in sent if isinstance(e, RequestSent)]

        assert r.paused and writes() == []  # the connection opened, nothing written
        r.step()
        for _ in range(200):
            if writes():
                break
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)
        assert [e.text for e in writes()] == ["Password"] and r.paused
        r.step()
        r.step()
        for _ in range(200):
            if len(writes()) == 3:
                break
            await asyncio.sleep(0.01)
        await asyncio.sleep(0.2)
        assert [e.text for e in writes()][1:] == ["Fetch Configuration Settings", "Sensor Request ch 12"]
        r.resume()
        result = await asyncio.wait_for(task, 20)
    assert result.ok and not result.stopped and result.writes == len(writes())


@pytest.mark.slow
async def test_stop_ends_the_replay_at_once(exchanges):
    sent: list = []
    async with simulator(seed=1) as sim:
        r = Replay(exchanges, options(sim.port, pace=Pace.RECORDED, rate=0.001), on_event=sent.append)
        task = asyncio.create_task(r.run())
        for _ in range(500):
            if any(isinstance(e, RequestSent) for e in sent):
                break
            await asyncio.sleep(0.01)
        r.stop()
        result = await asyncio.wait_for(task, 10)
    assert result.stopped and isinstance(sent[-1], Finished) and sent[-1].result is result
    assert result.writes < sum(len(p.sends) for p in r.plans)


async def test_unreachable_target_is_an_error_not_a_difference(exchanges):
    result = await replay(exchanges, options(closed_port()))
    assert result.exit_status == 2 and result.error.startswith(f"cannot connect to {LOCAL}:")


async def test_redacted_password_needs_one(exchanges):
    with pytest.raises(ReplayError, match="password is redacted"):
        Replay(exchanges, ReplayOptions(target=(LOCAL, 1))).check()


# -- planning --------------------------------------------------------------------------------------


def test_plan_selects_by_window_kind_and_connection(exchanges):
    start = exchanges.start_ns
    everything = plan(exchanges, Selection(), False)[0]
    assert all(len(s.items) == 1 for s in everything.sends)  # one frame per write
    times = [(s.t_ns - start) / 1e9 for s in everything.sends]
    lo, hi = times[3], times[-2]
    window = plan(exchanges, Selection(start_s=lo, end_s=hi), False)[0]
    assert [s.data for s in window.sends] == [s.data for s in everything.sends if lo <= (s.t_ns - start) / 1e9 < hi]
    switches = plan(exchanges, Selection(kinds=frozenset({"switch"})), False)[0]
    assert [s.data for s in switches.sends] == [b"rr1-7--1--0-ss1", b"rr1-7--0--0-ss1"]
    assert all("switch" in kinds_of(i) for s in switches.sends for i in s.items)
    assert plan(exchanges, Selection(conns=frozenset({2})), False) == []
    segments = plan(exchanges, Selection(), True)[0]
    assert b"".join(s.data for s in segments.sends) == b"".join(s.data for s in everything.sends)
    assert all(i.obs.item.kind is not ItemKind.PASSWORD for s in segments.sends for i in s.items)


# -- the command --------------------------------------------------------------------------------------


@pytest.mark.slow
async def test_command_exit_status_0_then_1_with_a_readable_diff(recorded, tmp_path):
    out = tmp_path / "cli.mcap"
    async with simulator(seed=1) as same, simulator(seed=2) as other:
        code, stdout, stderr = await run_process_async("replay", str(recorded), "--target", f"{LOCAL}:{same.port}",
                                             "--password", PASSWORD, "--compare", "exact", "-o", str(out))
        assert (code, stderr) == (0, ""), stdout
        assert "result: all answers matched" in stdout and f"wrote {out}" in stdout
        assert re.search(r"drift from schedule over \d+ writes: p50 [\d.]+ ms, p99 [\d.]+ ms, max [\d.]+ ms",
                         stdout)
        env = dict(os.environ, WHIZTAP_PASSWORD=PASSWORD)
        code, stdout, stderr = await run_process_async("replay", str(recorded), "--target", f"{LOCAL}:{other.port}",
                                             "--compare", "exact", "--pace", "lockstep", env=env)
    assert code == 1 and stderr == ""
    assert re.search(r"^MISMATCH c1 at \d+\.\d{6} s after rr1-12--0--0-ss1 \(Sensor Request ch 12\)$",
                     stdout, re.M)
    assert re.search(r"^  recorded +\| replayed$", stdout, re.M)
    assert re.search(r"^  sensor_value: \d+ +\| sensor_value: \d+$", stdout, re.M)
    assert "drift: none measured (pace lockstep keeps no schedule)" in stdout
    assert "DIFFERENCES (exit status 1)" in stdout


async def test_command_json_is_one_object_with_the_counts_and_every_difference(recorded):
    async with simulator(seed=1) as same, simulator(seed=2) as other:
        args = ["replay", str(recorded), "--password", PASSWORD, "--compare", "exact", "--pace", "lockstep",
                "--format", "json"]
        code_same, out_same, err_same = await run_process_async(*args, "--target", f"{LOCAL}:{same.port}")
        code, stdout, stderr = await run_process_async(*args, "--target", f"{LOCAL}:{other.port}", "--tolerance",
                                             "sensor_value=1")
    assert (code_same, err_same, code, stderr) == (0, "", 1, "")
    same_result, result = json.loads(out_same), json.loads(stdout)  # nothing but the object on stdout
    assert same_result["ok"] and same_result["differences"] == [] and same_result["exit_status"] == 0
    assert same_result["answers"]["mismatch"] == 0 and same_result["answers"]["match"] > 0
    assert not result["ok"] and result["exit_status"] == 1
    assert result["compare"] == {"mode": "exact", "tolerances": {"sensor_value": 1.0}, "ignore_fields": [],
                                 "ignore_kinds": []}
    assert len(result["differences"]) == result["answers"]["mismatch"] + result["answers"]["missing"] > 0
    first = result["differences"][0]
    assert (first["conn"], first["request"], first["status"]) == (1, "rr1-12--0--0-ss1", "mismatch")
    assert first["diff"].startswith("MISMATCH c1 at ") and first["recorded"].startswith("cr1-12--")
    assert result["drift"] is None and result["pace"] == "lockstep"


@pytest.mark.parametrize("args, message", [
    (["missing.mcap", "--target", "127.0.0.1:9"], "whiztap: missing.mcap: no such file"),
    (["{garbage}", "--target", "127.0.0.1:9"], "whiztap: {garbage}: not a readable recording (not an MCAP file"),
    (["{recorded}", "--target", "127.0.0.1:{closed}", "--password", "x"],
     "whiztap: cannot connect to 127.0.0.1:{closed}: Connection refused"),
    (["{recorded}", "--target", "127.0.0.1:9"],
     "whiztap: the recording's password is redacted: give --password or set WHIZTAP_PASSWORD"),
    (["{recorded}"], "whiztap: --target HOST:PORT is required (or --dry-run)"),
    (["{recorded}", "--target", "127.0.0.1:9", "--password", "x", "-o", "{garbage}/x.mcap"],
     "whiztap: cannot write {garbage}/x.mcap.part: Not a directory"),
    (["{recorded}", "--dry-run", "--tolerance", "speed=3"], "whiztap: --tolerance: unknown field 'speed'"),
    (["{recorded}", "--dry-run", "--kind", "dance"], "whiztap: --kind: unknown kind 'dance'"),
])
def test_command_errors_are_one_line_with_status_2(recorded, tmp_path, args, message):
    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"not an mcap file at all")
    closed = str(closed_port())
    fill = {"recorded": str(recorded), "garbage": str(garbage), "closed": closed}
    args = [a.format(**fill) for a in args]
    code, _stdout, stderr = run_cli("replay", *args)
    assert code == 2
    assert stderr.startswith(message.format(**fill)) and stderr.count("\n") == 1, stderr
    assert "Traceback" not in stderr


async def test_command_selection_options(recorded, exchanges):
    start = exchanges.start_ns
    [everything] = plan(exchanges, Selection(), True)
    times = [(s.t_ns - start) / 1e9 for s in everything.sends]
    lo, hi = times[1], times[-1]
    wanted = len(plan(exchanges, Selection(start_s=lo, end_s=hi), True)[0].sends)
    async with simulator(seed=1) as sim:
        code, stdout, stderr = await run_process_async(
            "replay", str(recorded), "--target", f"{LOCAL}:{sim.port}", "--password", PASSWORD, "--pace", "max",
            "--loop", "2", "--conn", "1", "--start", str(lo), "--end", str(hi), "--segments", "exact", "-q")
    assert (code, stderr) == (0, ""), stdout
    # each pass: the password, then the reads in the window
    assert f"replayed 2 connections, {2 * (wanted + 1)} writes; answers: " in stdout


def test_command_dry_run_prints_the_plan_and_sends_nothing(recorded):
    code, stdout, stderr = run_cli("replay", recorded, "--dry-run", "--kind", "sensor", "--segments", "frames")
    assert (code, stderr) == (0, "")
    sends = re.findall(r"^ +\d+\.\d{6} send (\S+)  (.*)$", stdout, re.M)
    assert len(sends) == 6 and all(text.startswith("Sensor Request ch ") for _, text in sends)
    assert len(re.findall(r"^ +expect cr1-", stdout, re.M)) == 6
    assert stdout.startswith("conn 1 (winsock,")


async def _interrupted(recorded, *args: str) -> tuple[int, bytes, bytes]:
    """A replay stopped by Ctrl-C once its first write has left: status, stdout, stderr."""
    async with simulator(seed=1) as sim:
        proc = await start_process("replay", recorded, "--target", f"{LOCAL}:{sim.port}", "--password", PASSWORD,
                                   "--rate", "0.001", *args)
        if "--format" in args:  # prints nothing until the end: the server has answered a first request
            await asyncio.wait_for(_until_answered(sim), WAIT)
        else:
            while b" c1 > " not in await asyncio.wait_for(proc.stdout.readline(), WAIT):
                pass  # until the first write has left
        proc.send_signal(signal.SIGINT)
        out, err = await asyncio.wait_for(proc.communicate(), WAIT)
    return proc.returncode, out, err


async def _until_answered(sim) -> None:
    while not sim.stats.answers_sent:
        await asyncio.sleep(0.01)


@pytest.mark.slow
async def test_ctrl_c_stops_the_replay_with_what_was_found_so_far_and_one_status(recorded):
    code, out, err = await _interrupted(recorded, "-v")
    assert code == 2 and err == b"whiztap: interrupted\n"
    assert re.search(rb"^replayed 1 connection, \d+ writes?; answers: ", out, re.M)
    assert b"result:" not in out  # 'interrupted' is the one status, not a verdict on half a replay too


@pytest.mark.slow
async def test_ctrl_c_in_json_says_the_status_the_command_exits_with(recorded):
    code, out, err = await _interrupted(recorded, "--format", "json")
    assert code == 2 and err == b"whiztap: interrupted\n"
    report = json.loads(out)
    assert report["stopped"] is True and report["exit_status"] == 2 and report["ok"] is False


@pytest.mark.slow
@pytest.mark.parametrize("sent", [b"", b"repl"])
async def test_a_client_that_never_finished_its_password_is_replayed_without_one(tmp_path, sent):
    """A port probe or health check (reads sendchkpass, leaves), or a client
    that left mid-password: the replay sends what it sent and nothing more, and
    finds no difference.  (A half-sent password needs the recording's kept
    secret to be replayed the same: redacted, it is sent as '*'s.)"""
    async def probe(port: int) -> list:
        reader, writer = await asyncio.open_connection(LOCAL, port)
        assert await reader.readexactly(11) == b"sendchkpass"
        writer.write(sent)
        await writer.drain()
        writer.close()
        return []

    path = tmp_path / "probe.mcap"
    async with simulator(seed=1) as sim, recording(sim.port, path, keep_secrets=bool(sent)) as rec:
        await probe(rec.proxy.port)
        await until_closed(sim)
        await rec.stop()
    recorded = load_exchanges(str(path))
    events: list = []
    async with simulator(seed=1) as sim:
        result = await replay(recorded, options(sim.port), events)
    assert result.ok, [d.diff for d in result.differences]
    written = [e for e in events if isinstance(e, RequestSent)]
    assert [len(e.data) for e in written] == ([len(sent)] if sent else [])  # never the whole password
