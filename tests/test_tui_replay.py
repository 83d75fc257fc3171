"""The replay screen: a recorded session replayed against the simulator from the TUI."""

import asyncio
import socket

import pytest

from whiztap.analyzer.cli.analyze import analyse_file
from whiztap.sniffer.sim.simulator import Simulator
from tests.tui_support import SAMPLES, SIZE, WAIT, loaded, until
from whiztap.tui.app import WhiztapApp
from whiztap.tui.screens.replay_screen import ReplayScreen
from whiztap.tui.data.sources import FileSource, FollowSource

# samples/clean-winsock.mcap was recorded from this simulator (samples/generate.py)
PASSWORD, SEED = "progwhiz", 1


async def open_screen(pilot, port: int, pace: str, rate: str = "1", output: str = "") -> ReplayScreen:
    await loaded(pilot)
    await pilot.press("r")
    screen = pilot.app.screen
    assert isinstance(screen, ReplayScreen)
    screen.query_one("#target").value = f"127.0.0.1:{port}"
    screen.query_one("#password").value = PASSWORD
    screen.query_one("#pace").value = pace
    screen.query_one("#rate").value = rate
    screen.query_one("#output").value = output
    return screen


@pytest.mark.slow
async def test_a_replay_against_the_same_robot_matches_and_is_saved(tmp_path):
    output = tmp_path / "replayed.mcap"
    async with Simulator(mode="winsock", password=PASSWORD, seed=SEED) as sim:
        app = WhiztapApp(FileSource(str(SAMPLES / "clean-winsock.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, sim.port, "max", output=str(output))
            await pilot.press("f5")
            await until(pilot, lambda: screen.runner.done, "the replay")
            runner = screen.runner
            assert runner.state == "finished" and runner.error is None
            assert runner.comparisons and all(c.match for c in runner.comparisons)
            assert runner.result.exit_status == 0
            await until(pilot, lambda: screen.comparisons.rows == len(runner.comparisons))
            status = str(screen.query_one("#replay-status").render())
            assert "FINISHED" in status and f"saved as {output}" in status
            await pilot.press("escape")
            assert not isinstance(app.screen, ReplayScreen)
    assert analyse_file(output, "dev-sum").frames > len(runner.comparisons)


@pytest.mark.slow
async def test_a_missing_password_is_asked_for_in_the_screen_s_own_terms(monkeypatch):
    monkeypatch.delenv("WHIZTAP_PASSWORD", raising=False)
    async with Simulator(mode="winsock", password=PASSWORD, seed=SEED) as sim:
        app = WhiztapApp(FileSource(str(SAMPLES / "clean-winsock.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, sim.port, "max")
            screen.query_one("#password").value = ""
            await pilot.press("f5")
            await until(pilot, lambda: screen.runner.done, "the replay to give up")
            assert screen.runner.error == "the recording's password is redacted: type it in Password"
            assert sim.stats.connections == 0


@pytest.mark.slow
async def test_step_sends_one_write_at_a_time_then_resume_runs_to_the_end():
    async with Simulator(mode="winsock", password=PASSWORD, seed=SEED) as sim:
        app = WhiztapApp(FileSource(str(SAMPLES / "clean-winsock.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, sim.port, "lockstep")
            await pilot.press("f7")  # starts paused, lets one write go: the password
            await until(pilot, lambda: screen.runner.sent == 1 and screen.runner.state == "paused", "one step")
            await pilot.press("f7")
            await until(pilot, lambda: screen.runner.sent == 2, "a second step")
            await pilot.pause(0.3)
            assert screen.runner.sent == 2 and screen.runner.state == "paused"
            await until(pilot, lambda: str(screen.query_one("#pause").label).startswith("Resume"))
            await pilot.press("f6")  # resume
            await until(pilot, lambda: screen.runner.done, "the rest of the replay")
            assert screen.runner.state == "finished" and screen.runner.sent > 20


@pytest.mark.slow
async def test_stop_ends_a_slow_replay_and_a_mismatch_shows_its_diff():
    async with Simulator(mode="winsock", password=PASSWORD, seed=SEED + 1, camera=False) as sim:
        app = WhiztapApp(FileSource(str(SAMPLES / "clean-winsock.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, sim.port, "recorded", rate="0.5")
            screen.query_one("#compare").value = "exact"
            await pilot.press("f5")
            await until(pilot, lambda: any(not c.match for c in screen.runner.comparisons), "a mismatch")
            await pilot.press("f8")
            await until(pilot, lambda: screen.runner.done, "the stop")
            assert screen.runner.state == "stopped"
            await until(pilot, lambda: screen.comparisons.rows == len(screen.runner.comparisons))
            row = next(i for i, c in enumerate(screen.runner.comparisons) if not c.match)
            screen.comparisons.focus()
            await pilot.press("g", *["j"] * row)
            await pilot.pause()
            diff = str(screen.query_one("#diff").render())
            assert "MISMATCH" in diff and "recorded" in diff and "replayed" in diff


@pytest.mark.slow
async def test_an_unreachable_target_is_one_line_on_the_screen():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]  # bound, not listening: refused
        app = WhiztapApp(FileSource(str(SAMPLES / "vpn.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, port, "max")
            await pilot.press("f5")
            await until(pilot, lambda: screen.runner.done, "the failure")
            assert screen.runner.state == "failed" and "cannot connect" in screen.runner.error
            await pilot.pause(0.2)
            assert "cannot connect" in str(screen.query_one("#replay-status").render())


@pytest.mark.slow
async def test_a_bad_target_is_refused_before_anything_starts():
    app = WhiztapApp(FileSource(str(SAMPLES / "vpn.mcap")))
    async with app.run_test(size=SIZE) as pilot:
        screen = await open_screen(pilot, 1, "max")
        screen.query_one("#target").value = "nowhere"
        await pilot.press("f5")
        await pilot.pause()
        assert screen.runner is None
        assert any("HOST:PORT" in n.message for n in app._notifications)


async def test_replay_needs_a_finished_recording(tmp_path):
    from tests.test_tui_live import GrowingRecording

    GrowingRecording(tmp_path / "g.mcap").flush()
    app = WhiztapApp(FollowSource(str(tmp_path / "g.mcap.part")))
    async with app.run_test(size=SIZE) as pilot:
        await pilot.press("r")
        assert not isinstance(app.screen, ReplayScreen)
        assert any("finished recording" in n.message for n in app._notifications)


@pytest.mark.slow
async def test_quitting_during_a_replay_stops_it():
    async with Simulator(mode="winsock", password=PASSWORD, seed=SEED) as sim:
        app = WhiztapApp(FileSource(str(SAMPLES / "clean-winsock.mcap")))
        async with app.run_test(size=SIZE) as pilot:
            screen = await open_screen(pilot, sim.port, "recorded", rate="0.05")  # would take half a minute
            await pilot.press("f5")
            await until(pilot, lambda: screen.runner.sent >= 2, "the replay to start")
            await pilot.press("ctrl+q")  # q would go into the focused target field
            await until(pilot, lambda: not app.is_running, "the app to quit")
        for _ in range(int(WAIT / 0.02)):  # the app is gone: wait without its pilot
            if screen.runner.done:
                break
            await asyncio.sleep(0.02)
        assert screen.runner.state == "stopped"
