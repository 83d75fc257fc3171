"""Traffic that keeps coming: following a growing recording, the proxy inside
the app in front of the simulator, and the demo."""

import asyncio
import io
import time
from pathlib import Path

import pytest
from rich.console import Console

from whiztap.analyzer.cli.analyze import analyse_file
from whiztap.analyzer.protocol.examples import CONFIG
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.format import metadata_record
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.analyzer.traffic import Closed, Data, Opened
from whiztap.sniffer.record.record_run import RecordSettings
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.sniffer.mitm.controller import Controller
from whiztap.tui.app import WhiztapApp
from whiztap.tui.data.controls import HeldKey
from whiztap.tui.demo import PASSWORD, DemoRig
from whiztap.tui.widgets.detail import describe_frame
from whiztap.tui.middle.inject import InjectScreen
from whiztap.tui.data.sources import FollowSource, LiveSource, ProxyRig

from tests.tui_support import SIZE, BesideAController, IdleShell, until

LOCAL = "127.0.0.1"
C2S, S2C = Direction.C2S, Direction.S2C


class GrowingRecording:
    """A recording written as ``whiztap record`` writes one: a real Recorder and
    RecordingFile, flushed when the test says so."""

    def __init__(self, path: Path, t_ns: int | None = None, split_duration_ns: int | None = None) -> None:
        metadata = metadata_record(source="test", split_duration=str(split_duration_ns or ""))
        self.file = RecordingFile(str(path), metadata, split_duration_ns=split_duration_ns)
        self.recorder = Recorder(self.file)
        self.t = time.time_ns() if t_ns is None else t_ns
        self.recorder.start(self.t)
        self.recorder.receive(Opened(1, self.t, "127.0.0.1:40000", "127.0.0.1:5000"))

    def exchange(self, request: bytes, answer: bytes) -> None:
        for direction, data in ((C2S, request), (S2C, answer)):
            self.t += 1_000_000
            self.recorder.receive(Data(1, direction, self.t, data))

    def flush(self) -> None:
        self.file.flush()

    def finish(self) -> None:
        self.recorder.receive(Closed(1, self.t, "client"))
        self.recorder.stop(self.t)


@pytest.mark.slow
async def test_follow_shows_what_the_recorder_flushes_and_stops_when_it_finishes(tmp_path):
    path = tmp_path / "growing.mcap"
    growing = GrowingRecording(path)
    growing.exchange(b"rr1-24--0--0-ss1", CONFIG)
    growing.flush()
    app = WhiztapApp(FollowSource(str(path) + ".part"))
    async with app.run_test(size=SIZE) as pilot:
        frames = app.frames
        await until(pilot, lambda: frames.rows == 2, "the first flush")
        assert frames.tail and frames.cursor == 1
        for value in range(5):
            growing.exchange(b"rr1-3--0--0-ss1", b"cr1-3--%d--0-ss1" % value)
        growing.flush()
        await until(pilot, lambda: frames.rows == 12, "the second flush")
        assert frames.cursor == 11  # following

        await pilot.press("k")  # the user looks back: the list stops following
        assert not frames.tail and frames.cursor == 10
        growing.exchange(b"rr1-0--0--2-ss1", b"cr1-0--4000--0-ss1")
        growing.flush()
        await until(pilot, lambda: frames.rows == 14, "the third flush")
        assert frames.cursor == 10 and frames.new_rows == 2
        assert "2 new" in frames.border_subtitle
        await pilot.press("end")  # follow again
        assert frames.tail and frames.cursor == 13 and frames.new_rows == 0

        assert not app.fed
        growing.finish()  # the recorder writes the index and renames the .part
        await until(pilot, lambda: app.fed, "the end of the recording")
        assert not Path(str(path) + ".part").exists() and path.exists()
        assert app.model.finished and "the recorder finished it" in app.sub_title
        assert app.model.connections()[0].state == "closed by client"


async def test_follow_goes_on_to_each_part_of_a_split_recording(tmp_path):
    path = tmp_path / "split.mcap"
    growing = GrowingRecording(path, split_duration_ns=10_000_000)
    growing.exchange(b"rr1-24--0--0-ss1", CONFIG)
    growing.flush()
    first = tmp_path / "split-0001.mcap.part"
    app = WhiztapApp(FollowSource(str(first)))
    async with app.run_test(size=SIZE) as pilot:
        frames = app.frames
        await until(pilot, lambda: frames.rows == 2, "part 1")
        for part in (2, 3):
            growing.t += 20_000_000
            growing.recorder.tick(growing.t)  # the split duration is over: a new part begins with the next read
            growing.exchange(b"rr1-3--0--0-ss1", b"cr1-3--%d--0-ss1" % part)
            assert Path(growing.file.current_path) == tmp_path / f"split-{part:04d}.mcap"
            growing.flush()
            await until(pilot, lambda part=part: frames.rows == 2 * part, f"part {part}")
            assert f"split-{part:04d}.mcap.part" in app.sub_title
        assert frames.tail and frames.cursor == 5
        growing.finish()
        await until(pilot, lambda: app.fed, "the end of the recording")
        assert "split-0003.mcap: the recorder finished it" in app.sub_title
        [connection] = app.model.connections()  # one connection, not one per part
        assert connection.state == "closed by client"
        # the answers of parts 2 and 3 were paired with requests as one session
        assert app.model.analyzer.summaries[1].notes == []


@pytest.mark.slow
async def test_live_mode_records_through_the_proxy_and_shows_frames_as_they_pass(tmp_path):
    output = tmp_path / "live.mcap"
    async with Simulator(mode="winsock", password="pw", seed=3) as sim:
        settings = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(output), quiet=True)
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            source = app.source
            await until(pilot, lambda: source.recording is not None and source.recording.proxy is not None,
                        "the proxy")
            assert str(source.recording.proxy.port) in app.sub_title
            frames = app.frames
            async with await Client.connect(LOCAL, source.recording.proxy.port, password="pw") as client:
                await client.fetch_configuration()
                await client.sensor(12)
                await until(pilot, lambda: frames.rows >= 7, "the first frames")
                assert frames.tail and frames.cursor == frames.rows - 1
                store = app.model.store
                assert b"pw" not in store.raws  # the password shows as '*', as it is recorded

                await pilot.press("k", "k")
                stopped_at = frames.cursor
                for _ in range(3):
                    await client.servo_position(0)
                await until(pilot, lambda: frames.new_rows == 6, "three more exchanges")
                assert frames.cursor == stopped_at and "6 new" in frames.border_subtitle
                await pilot.press("G")
                assert frames.tail and frames.cursor == frames.rows - 1
                [row] = app.model.connections()
                assert (row.mode, row.handshake, row.state) == ("winsock", "readytogo", "open")
            await pilot.press("q")  # finishes the recording first
            await until(pilot, lambda: not app.is_running, "the app to quit")
        shown = app.model.store.count
    assert read_metadata(str(output))["source"] == "proxy"
    analysis = analyse_file(output, "dev-sum")
    assert analysis.frames == shown and analysis.connections[0].handshake == "readytogo"


async def test_live_mode_says_so_when_it_cannot_listen(tmp_path):
    async with Simulator(mode="vpn") as sim:
        taken = sim.port  # the simulator holds it
        settings = RecordSettings((LOCAL, taken), (LOCAL, taken), str(tmp_path / "x.mcap"), quiet=True)
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            await until(pilot, lambda: not app.is_running, "the app to give up")
    assert app.error.startswith("cannot listen") and app.return_code == 2


@pytest.mark.slow
async def test_the_demo_runs_its_robot_live_and_finishes_demo_mcap_on_quit(tmp_path):
    output = tmp_path / "demo.mcap"
    app = WhiztapApp(LiveSource(DemoRig(str(output)), "demo"))
    async with app.run_test(size=SIZE) as pilot:
        store = app.model.store
        await until(pilot, lambda: len(store.violating) >= 6, "the demo's deliberate violations")
        handshakes = sorted(row.handshake for row in app.model.connections())
        assert handshakes == ["failed validation", "readytogo"]
        assert PASSWORD.encode() not in store.raws
        await pilot.press("g", "n")
        assert app.frames.frame == store.next_violation(0) and not app.frames.tail
        await pilot.press("q")
        await until(pilot, lambda: not app.is_running, "the app to quit")
    rules = set(analyse_file(output, "dev-sum").violation_counts)
    assert {"PW-SETCFG-CHECKSUM", "PW-FRAME-GARBAGE", "PW-HS-AFTER-FAILED"} <= rules


@pytest.mark.slow
def test_an_unexpected_failure_finishes_the_recording_says_where_it_is_and_exits_2(tmp_path, monkeypatch, capsys):
    """`whiztap demo` in-process, its screen broken on purpose once traffic flows:
    the recording is finished as q would finish it, the hints name it, and the
    failure is one line and a non-zero exit, not a traceback and status 0."""
    import sys

    import pytest
    import textual.constants

    from whiztap.analyzer.cli.root import main

    output = tmp_path / "live-demo.mcap"
    tick = WhiztapApp._tick

    def breaking_tick(app: WhiztapApp) -> None:
        if app.model.store.count >= 20:
            raise RuntimeError("broken on purpose")
        tick(app)

    monkeypatch.setattr(WhiztapApp, "_tick", breaking_tick)
    monkeypatch.setattr(textual.constants, "DRIVER", "textual.drivers.headless_driver:HeadlessDriver")
    for stream in (sys.stdin, sys.stdout):  # the demo wants a terminal; Textual's headless driver stands in
        monkeypatch.setattr(stream, "isatty", lambda: True)
    monkeypatch.setattr(sys, "argv", ["whiztap", "demo", "-o", str(output)])
    monkeypatch.delenv("WHIZTAP_DEBUG", raising=False)
    with pytest.raises(SystemExit) as ended:
        main()
    out, err = capsys.readouterr()
    assert ended.value.code == 2
    assert f"recorded {output}" in out and "no recording was written" not in out
    [line] = err.strip().splitlines()
    assert "unexpected error: RuntimeError: broken on purpose" in line and "Traceback" not in err
    assert read_metadata(str(output))["source"] == "proxy"  # finished: indexed, renamed from .part
    assert analyse_file(output, "dev-sum").frames >= 20


def test_the_hints_name_an_unfinished_recording_and_say_none_was_written_only_when_none_was(tmp_path):
    from whiztap.tui.cli import _hints

    path = tmp_path / "it's.mcap"
    assert _hints(str(path))[0] == f"no recording was written to {path}"
    Path(f"{path}.part").write_bytes(b"")
    said = "\n".join(_hints(str(path)))
    assert f"the recording was not finished: {path}.part" in said and "no recording" not in said
    assert "recover '" in said  # the path, quoted for a shell: it holds a '


# -- the proxy in the middle: counts, held frames, injection ---------------------------------------------------


@pytest.mark.slow
async def test_the_pane_the_list_and_the_detail_count_the_same_rows_with_frames_the_server_never_got(tmp_path):
    from whiztap.analyzer.mitm.spec import parse_fault
    from whiztap.analyzer.protocol.codec import encode
    from whiztap.analyzer.protocol.messages import SensorRequest
    from whiztap.sniffer.record.record_run import MiddleSettings

    drop = MiddleSettings(faults=(parse_fault("drop dir:c2s kind:command every:2"),))
    async with Simulator(mode="vpn", seed=7) as sim:
        settings = RecordSettings((LOCAL, 0), (LOCAL, sim.port), str(tmp_path / "live.mcap"), quiet=True, middle=drop)
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            source = app.source
            await until(pilot, lambda: source.recording is not None and source.recording.proxy is not None, "the proxy")
            _reader, writer = await asyncio.open_connection(LOCAL, source.recording.proxy.port)
            writer.write(b"".join(encode(SensorRequest(12 + n % 3)) for n in range(6)))
            store, frames = app.model.store, app.frames
            await until(pilot, lambda: store.count == 9 and frames.store_rows == 9,
                        "6 requests (3 dropped) and 3 answers")
            app.refresh_summaries()
            [row] = app.model.connections()
            assert row.frames == 9 == store.count  # the session saw 6 of them; the list shows 9
            assert str(app.connections.get_cell("1", "frames")) == "9"
            assert frames.border_subtitle == "following · 9"
            await until(pilot, lambda: app.detail.frame == frames.view[8], "the last frame in detail")
            assert "frame 9 of conn #1," in plain(app.detail.body.content)
            assert len(store.unseen[1]) == 3
            for place, n in enumerate(frames.view[row] for row in range(9)):  # a dropped one's too, not the session's
                assert f"frame {place + 1} of conn #1," in plain(describe_frame(store, n))
            writer.close()
            await app.action_quit()
            await until(pilot, lambda: not app.is_running, "the app to quit")


def plain(renderable) -> str:
    console = Console(file=io.StringIO(), width=100)
    console.print(renderable)
    return console.file.getvalue()


T0 = 1_700_000_000_000_000_000


def recording_beside_a_controller(tmp_path: Path) -> tuple[WhiztapApp, Controller, list[int]]:
    """The app on a small finished recording (its connection 1 closed), beside a
    Controller whose connection 1 holds a Sensor Request: (app, controller, clock)."""
    growing = GrowingRecording(tmp_path / "robot.mcap", t_ns=T0)
    growing.exchange(b"rr1-13--0--0-ss1", b"cr1-13--97--0-ss1")
    growing.finish()
    now = [T0]
    controller = Controller(seed=0, hold_timeout=60)
    controller.attach(lambda: now[0], lambda event: None)
    controller.set_intercept("kind:command ch:12")
    core, _ = controller.open(1, IdleShell())
    core.received(C2S, b"rr1-12--0--0-ss1", T0)
    return WhiztapApp(BesideAController(str(tmp_path / "robot.mcap"), controller)), controller, now


@pytest.mark.slow
async def test_a_held_frames_wait_and_countdown_tick_in_its_row_and_in_the_detail(tmp_path):
    app, _controller, now = recording_beside_a_controller(tmp_path)
    async with app.run_test(size=SIZE) as pilot:
        await until(pilot, lambda: app.fed and app.frames.rows == 3, "the recording and the held frame")
        await pilot.press("G")
        await until(pilot, lambda: isinstance(app.detail.frame, HeldKey), "the held frame in detail")
        assert "waiting 0 s; goes on as it is in 60 s" in plain(app.detail.body.content)
        for waited in (1, 2, 7):
            now[0] = T0 + waited * 1_000_000_000 + 300_000_000
            shown = f"waiting {waited} s; goes on as it is in {60 - waited} s"
            await until(pilot, lambda shown=shown: shown in plain(app.detail.body.content), shown)
            line = "".join(segment.text for segment in app.frames.render_line(2))
            assert f"#1, {60 - waited} s left:" in line
        assert app.frames.border_subtitle == "following · 2"  # the held frame is counted in the title
        assert "1 held" in str(app.frames.border_title)


async def test_inject_on_a_closed_connection_says_so_and_opens_no_dialog(tmp_path):
    app, controller, _ = recording_beside_a_controller(tmp_path)
    controller.closed(1)  # the proxy's connection 1 is gone; the recording's frames of it stay
    async with app.run_test(size=SIZE) as pilot:
        await until(pilot, lambda: app.fed and app.frames.rows == 2, "the recording")
        assert app.frames.frame == 0
        await pilot.press("I")
        assert not isinstance(app.screen, InjectScreen)
        assert any("conn #1 is closed" in n.message for n in app._notifications)
