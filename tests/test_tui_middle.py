"""The TUI's keys for the proxy in the middle, live, against the real proxy in
front of the simulator: intercept and edit (i, e), inject (I), the faults pane
(f), and a screen that stays live while frames are held; and the middle's
options of ``whiztap tui`` and ``whiztap demo``."""

from __future__ import annotations

import io
import json

import pytest
from rich.console import Console

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.sniffer.record.record_run import RecordSettings
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.tui.app import WhiztapApp
from whiztap.tui.widgets.detail import describe_frame
from whiztap.tui.middle.editor import EditorScreen
from whiztap.tui.screens.help import HelpScreen
from whiztap.tui.middle.inject import InjectScreen
from whiztap.tui.data.marks import mark_kind
from whiztap.tui.data.sources import LiveSource, ProxyRig

from tests.middle_support import Raw, answer_channel, sensor
from tests.record_support import read_all
from tests.cli_support import run_cli
from tests.tui_support import SAMPLES, SIZE, paste, until

LOCAL = "127.0.0.1"
C2S, S2C = Direction.C2S, Direction.S2C


def live_app(sim: Simulator, output) -> WhiztapApp:
    settings = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(output), quiet=True)
    return WhiztapApp(LiveSource(ProxyRig(settings), "live"))


async def proxy_port(pilot) -> int:
    source = pilot.app.source
    await until(pilot, lambda: source.recording is not None and source.recording.proxy is not None, "the proxy")
    return source.recording.proxy.port


async def quit_app(pilot) -> None:
    await pilot.press("q")  # finishes the recording first
    await until(pilot, lambda: not pilot.app.is_running, "the app to quit")


def rows_with(store, raw: bytes, direction: Direction) -> list[int]:
    return [n for n in range(store.count) if store.raw(n) == raw and store.direction(n) is direction]


def plain(renderable) -> str:
    console = Console(file=io.StringIO(), width=100)
    console.print(renderable)
    return console.file.getvalue()


@pytest.mark.slow
async def test_an_intercepted_sensor_request_is_edited_and_the_simulator_answers_the_edit(tmp_path):
    output = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        app = live_app(sim, output)
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            controller = app.source.controller
            await pilot.press("i")
            await paste(pilot, "kind:command ch:12")
            await pilot.press("enter")
            assert controller.intercept.text == "kind:command ch:12"
            frames = app.frames
            await until(pilot, lambda: "intercepting kind:command ch:12" in frames.border_title, "the title")
            await raw.send(sensor(12))
            await until(pilot, lambda: frames.held_frame is not None, "the held request under the cursor")
            assert "intercepting kind:command ch:12 · 1 held" in frames.border_title
            assert not rows_with(app.model.store, sensor(12), C2S)  # in the store once delivered, not before

            await pilot.press("e")
            await until(pilot, lambda: isinstance(app.screen, EditorScreen), "the editor")
            editor = app.screen
            assert isinstance(editor, EditorScreen) and editor.typed_input.value == "rr1-12--0--0-ss1"
            await pilot.press("home", *["right"] * 6, "backspace", "3")  # rr1-12 -> rr1-13
            assert editor.typed_input.value == "rr1-13--0--0-ss1"
            assert "Sensor Request ch 13" in plain(editor.query_one("#preview").content)
            await pilot.press("enter")
            await until(pilot, lambda: app.screen is not editor, "the editor to close")
            [answer] = await raw.take(1)
            assert answer_channel(answer) == 13  # the simulator got the edited frame
            store = app.model.store
            await until(pilot, lambda: rows_with(store, sensor(13), C2S), "the delivered request")
            [row] = rows_with(store, sensor(13), C2S)
            await until(pilot, lambda: any(m.action == "edit" for m in store.marks.get(row, ())), "its marks")
            await until(pilot, lambda: frames.held_frame is None and "held" not in frames.border_title,
                        "the title without the held frame")
            shown = plain(describe_frame(store, row))
            assert "What the proxy did" in shown and "rr1-12--0--0-ss1" in shown and "hand edit (held #1)" in shown
            await raw.close()
            await quit_app(pilot)
    [edit] = [i for i in read_all(str(output))["/interventions"] if i["action"] == "edit"]
    assert (edit["before"], edit["after"], edit["dir"]) == ("rr1-12--0--0-ss1", "rr1-13--0--0-ss1", "c2s")
    assert (edit["cause"], edit["held"]) == ("hand edit", 1)


@pytest.mark.slow
async def test_an_injected_sensor_request_pairs_with_its_answer(tmp_path):
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        app = live_app(sim, tmp_path / "live.mcap")
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            store = app.model.store
            await raw.send(sensor(14))
            await raw.take(1)
            await until(pilot, lambda: app.frames.frame is not None and store.count == 2, "the first exchange")

            await pilot.press("I")
            await until(pilot, lambda: isinstance(app.screen, InjectScreen), "the dialog")
            dialog = app.screen
            assert isinstance(dialog, InjectScreen) and dialog.conn == 1 and dialog.direction is C2S
            await paste(pilot, "sensor 12")
            await pilot.press("enter")
            await until(pilot, lambda: app.screen is not dialog, "the dialog to close")
            [answer] = (await raw.take(2))[1:]  # the client gets the answer to a request it never sent
            assert answer_channel(answer) == 12
            await until(pilot, lambda: any(store.pair[n] >= 0 for n in rows_with(store, sensor(12), C2S)),
                        "the injected request and its answer")
            [request] = rows_with(store, sensor(12), C2S)
            assert [m.action for m in store.marks[request]] == ["inject"]
            reply = store.pair[request]
            assert store.pair[reply] == request and store.kind(reply) is ItemKind.RESPONSE
            assert store.raw(reply) == answer

            await pilot.press("I")
            await until(pilot, lambda: isinstance(app.screen, InjectScreen), "the dialog again")
            await pilot.press("up")  # the history recalls what was injected
            assert app.screen.typed_input.value == "sensor 12"
            await pilot.press("escape")
            await raw.close()
            await quit_app(pilot)


@pytest.mark.slow
async def test_a_fault_added_in_the_faults_pane_drops_every_second_answer(tmp_path):
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        app = live_app(sim, tmp_path / "live.mcap")
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            controller = app.source.controller
            pane = app.faults
            await pilot.press("f")
            assert pane.table.has_focus and app.tabs.active == "faults"
            await pilot.press("a")
            await paste(pilot, "drop dir:sideways")
            await until(pilot, lambda: "dir: wants c2s or s2c" in str(pane.query_one("#fault-error").content),
                        "the error under the field")
            assert not controller.faults  # nothing applied while typing
            await pilot.press("ctrl+u", *"dro")
            await until(pilot, lambda: pane.spec._suggestion == "drop", "the completion")
            await pilot.press("tab")
            await paste(pilot, " dir:s2c kind:response every:2")
            await pilot.press("enter")
            await until(pilot, lambda: bool(controller.faults), "the fault")
            [fault] = controller.faults
            assert fault.spec.text == "drop dir:s2c kind:response every:2" and pane.table.has_focus
            await pilot.press("escape")
            assert app.frames.has_focus

            store = app.model.store
            channels = (12, 13, 14, 15)
            for ch in channels:
                await raw.send(sensor(ch))
                await until(pilot, lambda ch=ch: any(store.raw(n).startswith(b"cr1-%d--" % ch)
                                                     for n in range(store.count)), f"the answer on {ch}")
            got = await raw.nothing_more(2)
            assert [answer_channel(a) for a in got] == [12, 14]  # every second answer dropped
            answers = [n for n in range(store.count) if store.kind(n) is ItemKind.RESPONSE]
            await until(pilot, lambda: len(store.marked) >= 2, "the drop marks")
            marks = [[mark_kind(m) for m in store.marks.get(n, ())] for n in answers]
            assert marks == [[], ["dropped"], [], ["dropped"]]
            for n, dropped in zip(answers, (False, True, False, True)):
                request = store.pair[n]  # the server answered every request
                unanswered = [v for v in store.violations.get(request, ()) if v.rule_id == "PW-PAIR-UNANSWERED"]
                assert bool(unanswered) == dropped
                assert all(v.detail.startswith("client side") for v in unanswered)
            assert fault.hits == 2
            pane.show()
            assert pane.table.get_row_at(0)[2] == "2"
            await raw.close()
            await quit_app(pilot)


@pytest.mark.slow
async def test_keys_are_answered_while_a_hundred_frames_are_held(tmp_path):
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        app = live_app(sim, tmp_path / "live.mcap")
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            controller = app.source.controller
            frames = app.frames
            await pilot.press("i")
            await paste(pilot, "kind:command")
            await pilot.press("enter")
            await raw.send(*[sensor(12 + n % 12) for n in range(100)])
            await until(pilot, lambda: len(controller.held.frames) == 100 and frames.rows == 100, "100 held frames")
            assert "100 held" in frames.border_title and frames.held_frame is not None
            await pilot.press("g")  # first row, not following
            assert frames.cursor == 0 and not frames.tail
            await pilot.press("j", "j", "j")
            assert frames.cursor == 3
            await pilot.press("question_mark")
            assert isinstance(app.screen, HelpScreen)
            await pilot.press("escape", "G")
            assert frames.tail and frames.cursor == 99 and frames.held_frame.id == 100
            await pilot.press("x")  # drop the last one: a row of the list now, marked dropped
            await until(pilot, lambda: len(controller.held.frames) == 99 and frames.store_rows == 1, "the drop")
            assert [m.action for m in app.model.store.marks[0]] == ["hold", "drop"] and frames.rows == 100
            await pilot.press("A")  # let the others go
            answers = await raw.nothing_more(99)
            assert len(answers) == 99 and not controller.held.frames
            await raw.close()
            await quit_app(pilot)


def test_the_middle_options_go_with_the_live_proxy_only():
    result = run_cli("tui", SAMPLES / "vpn.mcap", "--fault", "drop dir:s2c")
    assert result.returncode == 2 and "they go with --upstream" in result.stderr
    result = run_cli("tui", "--upstream", "127.0.0.1:5000", "--fault", "drop nowhere:1")
    assert result.returncode == 2 and "nowhere:1" in result.stderr


@pytest.mark.slow
def test_the_demo_runs_in_the_middle_with_the_faults_it_is_given(tmp_path):
    output = tmp_path / "demo.mcap"
    result = run_cli("demo", "--headless", "--seconds", "1", "-o", output, "--fault", "delay:1ms dir:s2c",
                 "--seed", "3")
    assert result.returncode == 0, result.stderr
    metadata = read_metadata(str(output))
    assert metadata["middle"] == "yes" and metadata["seed"] == "3"
    assert json.loads(metadata["faults"]) == [{"name": "", "spec": "delay:1ms dir:s2c"}]
    assert any(i["action"] == "delay" for i in read_all(str(output))["/interventions"])


async def test_a_script_that_raises_is_a_notice_on_the_screen_not_a_traceback_over_it(tmp_path, capfd):
    """Live, the proxy's warnings (a script's hook that raised) go to the
    screen: on stderr they would be written over the running app."""
    script = tmp_path / "broken.py"
    script.write_text("def frame(flow):\n    raise RuntimeError('broken on purpose')\n")
    output = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        from whiztap.sniffer.record.record_run import MiddleSettings

        settings = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(output), quiet=True,
                                  middle=MiddleSettings(scripts=(str(script),), always=True))
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            await raw.send(sensor(12))
            [answer] = await raw.take(1)
            assert answer_channel(answer) == 12  # the frame passed untouched
            await until(pilot, lambda: any("broken.py" in n.message for n in app._notifications), "the notice")
            [notice] = [n for n in app._notifications if "broken.py" in n.message]
            assert "RuntimeError: broken on purpose" in notice.message and notice.severity == "warning"
            await raw.close()
            await quit_app(pilot)
    assert "broken on purpose" not in capfd.readouterr().err


@pytest.mark.slow
async def test_frames_held_at_the_proxy_are_not_counted_as_new_frames(tmp_path):
    """Away from the end, "N new (End follows)" counts frames that arrived;
    a held frame is a row too, but not a new frame (it was counted as one)."""
    output = tmp_path / "live.mcap"
    async with Simulator(port=0, mode="vpn", seed=7) as sim:
        app = live_app(sim, output)
        async with app.run_test(size=SIZE) as pilot:
            raw = await Raw.open(await proxy_port(pilot))
            frames = app.frames
            await raw.send(sensor(13))
            await raw.take(1)
            await until(pilot, lambda: frames.store_rows == 2, "the first exchange")
            await pilot.press("i")
            await paste(pilot, "kind:command ch:12")
            await pilot.press("enter")
            await until(pilot, lambda: "intercepting" in frames.border_title, "the intercept")
            await pilot.press("g")  # away from the end: not following
            assert not frames.tail
            await raw.send(sensor(12))
            await until(pilot, lambda: frames.held_frame is not None or frames.rows == 3, "the held row")
            await pilot.pause(0.3)
            assert frames.rows == 3 and "new" not in str(frames.border_subtitle), frames.border_subtitle
            await pilot.press("A")  # let it go: the request and its answer are new frames
            await until(pilot, lambda: frames.store_rows == 4, "the released request and its answer")
            assert "2 new (End follows)" in str(frames.border_subtitle)
            await raw.close()
            await quit_app(pilot)
