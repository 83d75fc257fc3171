"""Snapshots of the main screens (pytest-textual-snapshot), from fixed recordings.

The data are the committed samples and a recording written here with fixed
timestamps; nothing on these screens reads the clock (times are the recorded
ones, in UTC).  Update after a deliberate change with ``--snapshot-update`` and
look at the SVGs in tests/__snapshots__/ before committing them.
"""

import pytest

from tests.test_tui_live import GrowingRecording
from tests.tui_support import ROOT, loaded, settled, until
from whiztap.tui.app import WhiztapApp
from whiztap.tui.data.sources import FileSource, FollowSource

SIZE = (120, 36)


@pytest.fixture(autouse=True)
def fixed_world(monkeypatch):
    monkeypatch.chdir(ROOT)  # sample paths in titles are relative
    monkeypatch.delenv("WHIZTAP_PASSWORD", raising=False)


def sample(name: str) -> WhiztapApp:
    return WhiztapApp(FileSource(f"samples/{name}"))


def pressing(*keys: str):
    """What to do before the snapshot: wait for the recording, press ``keys``, let the panes settle."""
    async def run_before(pilot):
        await loaded(pilot)
        await pilot.press(*keys)
        await settled(pilot)

    return run_before


@pytest.mark.slow
def test_frames_with_a_violation_in_detail(snap_compare):
    assert snap_compare(sample("violations.mcap"), terminal_size=SIZE, run_before=pressing("n", "n"))


@pytest.mark.slow
def test_statistics(snap_compare):
    assert snap_compare(sample("vpn.mcap"), terminal_size=SIZE, run_before=pressing("s"))


@pytest.mark.slow
def test_a_filtered_list(snap_compare):
    async def responses(pilot):
        await loaded(pilot)
        await pilot.press("slash", *"kind:response ch:12", "enter")
        await loaded(pilot)
        await pilot.press("j", "j")
        await settled(pilot)

    assert snap_compare(sample("vpn.mcap"), terminal_size=SIZE, run_before=responses)


@pytest.mark.slow
def test_help(snap_compare):
    async def help_screen(pilot):
        await loaded(pilot)
        await settled(pilot)
        await pilot.press("question_mark")

    assert snap_compare(sample("failed-password.mcap"), terminal_size=SIZE, run_before=help_screen)


@pytest.mark.slow
def test_replay_screen(snap_compare):
    async def replay(pilot):
        await loaded(pilot)
        await pilot.press("r")

    assert snap_compare(sample("clean-winsock.mcap"), terminal_size=SIZE, run_before=replay)


@pytest.mark.slow
def test_following_with_new_frames_waiting(snap_compare, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    growing = GrowingRecording(tmp_path / "robot.mcap", t_ns=1_700_000_000_000_000_000)
    growing.exchange(b"rr1-24--0--0-ss1", b"sr1-\x04000000101200-ss1")
    for value in range(8):
        growing.exchange(b"rr1-3--0--0-ss1", b"cr1-3--%d--0-ss1" % (100 + value))
    growing.flush()

    async def look_back(pilot):
        frames = pilot.app.frames
        await until(pilot, lambda: frames.rows == 18)
        await pilot.press("k", "k", "k")
        for value in range(3):
            growing.exchange(b"rr1-0--0--2-ss1", b"cr1-0--%d--0-ss1" % (4000 + value))
        growing.flush()
        await until(pilot, lambda: frames.rows == 24)
        await settled(pilot)

    app = WhiztapApp(FollowSource("robot.mcap.part"))
    assert snap_compare(app, terminal_size=SIZE, run_before=look_back)
