"""One verdict everywhere: the same faulted session through the real proxy in
the middle in front of the simulator (an injected request, whose answer the
client never asked for, and an answer the proxy dropped), judged by the live
TUI, the control API's ``GET /state``, ``record``'s closing summary and
``whiztap analyze`` of the file; all four say the same."""

from __future__ import annotations

import json

from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.analyzer.protocol.codec import encode
from whiztap.analyzer.protocol.messages import FetchConfiguration
from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.record.record_run import MiddleSettings, RecordSettings
from whiztap.sniffer.record.summary import summary_lines
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.tui.app import WhiztapApp
from whiztap.tui.data.model import verdict_text
from whiztap.tui.data.sources import LiveSource, ProxyRig

from tests.middle_support import Raw, answer_channel, sensor
from tests.test_control_api import ok
from tests.cli_support import run_cli
from tests.test_tui_middle import LOCAL, proxy_port, quit_app
from tests.tui_support import SIZE, until

DROP_ANSWER_14 = "drop dir:s2c kind:response ch:14 nth:1"


async def test_the_tui_the_api_the_summary_and_analyze_give_one_verdict(tmp_path):
    output = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        middle = MiddleSettings(faults=(parse_fault(DROP_ANSWER_14),), control=Endpoint(path=""))
        rig = ProxyRig(RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(output), quiet=True, middle=middle))
        app = WhiztapApp(LiveSource(rig, "live"))
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            await raw.send(encode(FetchConfiguration()))  # then every sensor request is certain to await an answer
            await raw.take(1)
            await raw.send(sensor(12))
            await raw.take(2)
            app.source.controller.inject(1, "c2s", "sensor 13")  # the client gets an answer it never asked for
            await raw.take(3)
            await raw.send(sensor(14))  # its answer is dropped: the client waits for it in vain
            assert [answer_channel(a) for a in (await raw.nothing_more(3))[1:]] == [12, 13]
            await raw.close()

            model = app.model
            await until(pilot, lambda: model.verdict().connections == 1 and model.analyzer.open_connections == 0,
                        "the connection judged in the TUI")
            state = {}
            for _ in range(100):  # the writer reports its verdict as it changes
                state = (await ok(rig.recording, "GET", "/state"))["verdict"] or {}
                if state.get("connections") == 1 and state.get("open") == 0:
                    break
                await pilot.pause(0.05)
            assert state.get("open") == 0, state
            tui = model.verdict()
            app.refresh_summaries()
            await pilot.pause()
            assert verdict_text(tui) in str(app.status.content)
            await quit_app(pilot)
    summary = rig.recording.summary
    result = run_cli("analyze", output, "--format", "json")
    report = json.loads(result.stdout)

    assert tui.by_rule == {"PW-PAIR-UNANSWERED": 1}  # the dropped answer: the client's request unanswered
    assert tui.effects_by_severity["error"] == 1  # the injection's answer, unsolicited by the client
    by_severity = report["summary"]["violations_by_severity"]
    assert tui.by_severity == state["violations"] == summary["violations"] == by_severity
    assert tui.by_rule == state["rules"] == summary["verdict"]["rules"] == report["rule_counts"]
    assert tui.effects_by_severity == state["effects"] == summary["verdict"]["effects"] == \
        report["interventions"]["effects_by_severity"]
    assert state["interventions"] == summary["verdict"]["interventions"] == report["interventions"]["count"] >= 2
    assert tui.passed == state["passed"] == summary["verdict"]["passed"] == report["passed"] is False
    assert result.returncode == 1
    errors = by_severity["error"]
    assert f"violations: {errors} error" in "\n".join(summary_lines({**summary, "size": 0}, "recorded"))
