"""The TUI on sample recordings, driven by key presses as a user would."""

import contextlib

import pytest
from textual import events

from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.recording.info import recording_info
from whiztap.analyzer.traffic import Data, Opened
from tests.tui_support import SAMPLES, SIZE, frames_shown, loaded, settled, until
from whiztap.tui.app import WhiztapApp
from whiztap.tui.screens.help import HelpScreen
from whiztap.tui.data.sources import FileSource
from tests.test_tui_live import GrowingRecording


@contextlib.asynccontextmanager
async def loaded_app(name: str):
    """The app on a sample recording, run headless until the recording is loaded: (app, pilot)."""
    app = WhiztapApp(FileSource(str(SAMPLES / name)))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        yield app, pilot


async def test_a_recording_opens_on_its_first_frame_with_its_connections():
    async with loaded_app("clean-winsock.mcap") as (app, pilot):
        store = app.model.store
        assert app.frames.rows == store.count > 0
        assert app.frames.cursor == 0 and app.detail.frame == 0
        assert not app.frames.tail  # a recording does not follow
        await settled(pilot)
        assert "1" in app.connections.rows and "all" in app.connections.rows
        status = str(app.status.render())
        assert f"{store.count:,} frames" in status


@pytest.mark.slow
async def test_vim_keys_move_the_cursor_and_the_detail_follows():
    async with loaded_app("vpn.mcap") as (app, pilot):
        last = app.frames.rows - 1
        await pilot.press("j", "j", "down")
        assert app.frames.cursor == 3
        await pilot.press("k")
        assert app.frames.cursor == 2
        await pilot.press("G")
        assert app.frames.cursor == last and app.frames.tail
        await pilot.press("g")
        assert app.frames.cursor == 0 and not app.frames.tail
        await pilot.press("end")
        assert app.frames.cursor == last
        await pilot.press("home", "pagedown")
        assert app.frames.cursor > 10
        await pilot.press("pageup")
        assert app.frames.cursor == 0
        await pilot.pause()
        assert app.detail.frame == 0


@pytest.mark.slow
async def test_n_and_N_walk_the_violations_in_order():
    async with loaded_app("violations.mcap") as (app, pilot):
        store = app.model.store
        seen = []
        for _ in range(5):
            await pilot.press("n")
            seen.append(app.frames.frame)
        assert seen == store.violating[:5]
        await pilot.press("N", "N")
        assert app.frames.frame == store.violating[2]
        await pilot.pause()
        assert app.detail.frame == store.violating[2]
        await pilot.press("G", "n")  # nothing after the last one: the cursor stays
        assert app.frames.cursor == app.frames.rows - 1


@pytest.mark.slow
async def test_p_jumps_between_a_request_and_its_response():
    async with loaded_app("clean-winsock.mcap") as (app, pilot):
        store = app.model.store
        request = next(n for n in range(store.count)
                       if store.kind(n) is ItemKind.COMMAND and store.pair[n] >= 0)
        for _ in range(request):
            await pilot.press("j")
        await pilot.press("p")
        response = app.frames.frame
        assert store.pair[response] == request and store.direction(response) is Direction.S2C
        await pilot.press("p")
        assert app.frames.frame == request


@pytest.mark.slow
async def test_the_filter_bar_narrows_the_list_and_an_empty_filter_restores_it():
    async with loaded_app("vpn.mcap") as (app, pilot):
        total = app.frames.rows
        await pilot.press("slash")
        assert app.filter_bar.has_focus
        await pilot.press(*"kind:response ch:12", "enter")
        await until(pilot, lambda: app.frames.view.complete and app.frames.rows == len(app.frames.view))
        store = app.model.store
        shown = frames_shown(app)
        assert shown and all(store.kind(n) is ItemKind.RESPONSE for n in shown)
        assert all("ch 12" in store.meaning(n) for n in shown)
        assert app.frames.has_focus and "kind:response ch:12" in str(app.status.render())
        await pilot.press("slash", "home", "ctrl+k", "enter")  # an empty filter
        await until(pilot, lambda: app.frames.rows == total)
        assert app.frames.view.all


@pytest.mark.slow
async def test_free_text_and_violations_only_in_the_filter():
    async with loaded_app("violations.mcap") as (app, pilot):
        await pilot.press("slash", *"violations junk", "enter")
        await until(pilot, lambda: app.frames.view.complete and app.frames.rows == len(app.frames.view))
        store = app.model.store
        shown = frames_shown(app)
        assert shown and all(store.violations.get(n) for n in shown)
        assert all("junk" in store.observation(n).item.raw.decode("latin-1") for n in shown)


@pytest.mark.slow
async def test_a_bad_filter_is_refused_on_the_bar_and_the_filter_in_force_stays():
    async with loaded_app("vpn.mcap") as (app, pilot):
        await pilot.press("slash", *"kind:response", "enter")
        await until(pilot, lambda: app.frames.view.complete and app.frames.rows == len(app.frames.view))
        shown = frames_shown(app)
        await pilot.press("slash", *" dir:sideways", "enter")
        await pilot.pause()
        bar = app.filter_bar
        assert frames_shown(app) == shown and app.filter_text == "kind:response"
        status = str(app.status.render())
        assert "filter: kind:response →" in status and "sideways" not in status  # not shown as applied
        assert bar.has_class("-invalid") and bar.has_focus
        assert "c2s or s2c" in str(bar.border_subtitle) and "in force: kind:response" in str(bar.border_subtitle)
        await pilot.press("escape")  # the words in force come back
        assert app.frames.has_focus and bar.value == "kind:response" and not bar.has_class("-invalid")


@pytest.mark.slow
async def test_choosing_a_connection_shows_only_its_frames():
    async with loaded_app("violations.mcap") as (app, pilot):
        await settled(pilot)
        await pilot.press("c")
        assert app.connections.has_focus
        await pilot.press("j", "down", "enter")  # below "all" and connection 1
        await until(pilot, lambda: app.frames.view.complete and app.frames.rows == len(app.frames.view))
        store = app.model.store
        assert {store.conn[n] for n in frames_shown(app)} == {2}
        assert app.frames.has_focus
        await pilot.press("c", "g", "enter")  # "all"
        await until(pilot, lambda: app.frames.view.all and app.frames.rows == store.count)


async def test_the_connections_pane_shows_every_row_while_there_is_room(tmp_path):
    path = tmp_path / "eight.mcap"
    recording = GrowingRecording(path)  # connection 1, and seven more
    for conn in range(2, 9):
        recording.recorder.receive(Opened(conn, recording.t, f"127.0.0.1:{40000 + conn}", "127.0.0.1:5000"))
        recording.recorder.receive(Data(conn, Direction.C2S, recording.t + conn, b"rr1-12--0--0-ss1"))
    recording.finish()
    app = WhiztapApp(FileSource(str(path)))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        await settled(pilot)
        pane = app.connections
        assert len(pane.rows) == 9  # "all" and eight connections
        assert pane.max_scroll_y == 0 and pane.size.height >= 10  # each row on screen, with the header


async def test_help_opens_over_the_list_and_closes():
    async with loaded_app("vpn.mcap") as (app, pilot):
        await pilot.press("question_mark")
        assert isinstance(app.screen, HelpScreen)
        await pilot.press("j", "slash")  # the main screen's keys do nothing meanwhile
        assert app.frames.cursor == 0 and not app.filter_bar.has_class("shown")
        await pilot.press("escape")
        assert not isinstance(app.screen, HelpScreen)


@pytest.mark.slow
async def test_the_stats_pane_shows_rates_latencies_and_a_plot_per_channel():
    async with loaded_app("vpn.mcap") as (app, pilot):
        await pilot.press("s")
        await pilot.pause()
        assert app.tabs.active == "stats"
        latency = str(app.stats.query_one("#latency").render())
        assert "Sensor Request" in latency and "p99" in latency
        await until(pilot, lambda: len(app.stats.query("ChannelPlot")) == len(app.model.channel_values()))
        plots = {(p.kind, p.channel) for p in app.stats.query("ChannelPlot")}
        assert ("servo", 2) in plots and ("sensor", 12) in plots
        span = recording_info(SAMPLES / "vpn.mcap")["duration_s"]  # first to last timestamp of the file
        assert f"over the recording's {span:.3f} s" in str(app.stats.rate_title.render())
        await pilot.press("d")
        assert app.tabs.active == "detail"


@pytest.mark.slow
async def test_s_pressed_twice_at_once_draws_the_plots():
    """The second s came while the first one's plots were mounted but not yet
    composed: updating one looked for its sparkline and found nothing."""
    async with loaded_app("vpn.mcap") as (app, pilot):
        for _ in range(2):  # both keys queued before the app deals with either, as a quick typist sends them
            app.post_message(events.Key("s", "s"))
        await settled(pilot)
        assert app.tabs.active == "stats" and app.is_running
        plots = app.stats.plot_of
        assert set(plots) == set(app.model.channel_values())
        assert all(plot.sparkline.data for plot in plots.values())


async def test_q_quits():
    async with loaded_app("vpn.mcap") as (app, pilot):
        await pilot.press("q")
        await pilot.pause()
        assert not app.is_running


async def test_z_gives_the_list_the_whole_width_and_d_brings_the_pane_back():
    async with loaded_app("vpn.mcap") as (app, pilot):
        narrow = app.frames.size.width
        await pilot.press("z")
        await pilot.pause()
        assert app.frames.size.width > narrow and not app.tabs.display
        await pilot.press("d")
        await pilot.pause()
        assert app.frames.size.width == narrow and app.tabs.active == "detail"


async def test_a_recording_cut_short_shows_what_was_complete_and_says_how_to_recover(tmp_path):
    crashed = GrowingRecording(tmp_path / "crashed.mcap")  # flushed, never finished: a crash leftover
    crashed.exchange(b"rr1-24--0--0-ss1", b"sr1-\x01200-ss1")
    crashed.flush()
    app = WhiztapApp(FileSource(str(tmp_path / "crashed.mcap.part")))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        assert app.model.store.count == 2
        assert any("whiztap recover" in n.message for n in app._notifications)


def test_the_detail_cites_the_section_of_the_message_a_violation_is_in():
    """A channel out of range in a response is cited by the response's
    section, not the rule's own (the Servo Position Request's)."""
    from rich.console import Console

    from whiztap.analyzer.protocol.frame_text import frame_alone
    from whiztap.analyzer.protocol.observations import Direction
    from whiztap.tui.widgets.detail import violations_text

    [observation], _ = frame_alone(b"cr1-99--5--0-ss1", Direction.S2C)
    [violation] = [v for v in observation.violations if v.rule_id == "PW-RANGE-CHANNEL"]
    assert violation.section != violation.rule.section
    console = Console(width=200, file=None)
    with console.capture() as shown:
        console.print(violations_text([violation]))
    assert f"(error, {violation.section})" in shown.get() and violation.rule.section not in shown.get()
