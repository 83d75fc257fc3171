"""Snapshots of the panes of the proxy in the middle (pytest-textual-snapshot):
a held frame in the list, the editor with a frame that breaks a rule, the
inject dialog, and the faults pane with two faults.

Nothing here moves: the frames come from a recording written in the test with
fixed times, and the Controller beside it is driven by no proxy, with a clock
that stands still (its held frame has waited exactly 2.5 s).  Update after a
deliberate change with ``--snapshot-update`` and look at the SVGs in
tests/__snapshots__/ before committing them.
"""

from __future__ import annotations

import pytest

from whiztap.analyzer.protocol.observations import Direction
from whiztap.sniffer.mitm.controller import Controller
from whiztap.tui.app import WhiztapApp
from whiztap.tui.data.controls import HeldKey

from tests.test_tui_live import GrowingRecording
from tests.tui_support import BesideAController, IdleShell, loaded, paste, settled, until

SIZE = (120, 36)
T0 = 1_700_000_000_000_000_000
WAITED_NS = 2_500_000_000


@pytest.fixture
def controller() -> Controller:
    now = [T0]
    controller = Controller(seed=0)
    controller.attach(lambda: now[0], lambda event: None)
    controller.set_intercept("kind:command ch:12")
    core, _ = controller.open(1, IdleShell())
    core.received(Direction.C2S, b"rr1-12--0--0-ss1", T0)  # held: the lane has nowhere to write it anyway
    now[0] += WAITED_NS
    return controller


@pytest.fixture
def app(tmp_path, monkeypatch, controller) -> WhiztapApp:
    monkeypatch.chdir(tmp_path)
    growing = GrowingRecording(tmp_path / "robot.mcap", t_ns=T0)
    growing.exchange(b"rr1-24--0--0-ss1", b"sr1-\x04000000101200-ss1")
    for ch, value in ((12, 431), (13, 97), (12, 433), (14, 1010)):
        growing.exchange(b"rr1-%d--0--0-ss1" % ch, b"cr1-%d--%d--0-ss1" % (ch, value))
    growing.finish()
    return WhiztapApp(BesideAController("robot.mcap", controller))


async def on_the_held_frame(pilot) -> None:
    app = pilot.app
    await loaded(pilot)
    await pilot.press("G")
    await until(pilot, lambda: isinstance(app.detail.frame, HeldKey), "the held frame in detail")
    await settled(pilot)


async def steady(pilot) -> None:
    """The focused line's cursor stops blinking (the one thing that moves)."""
    pilot.app.screen.focused.cursor_blink = False
    await pilot.pause()


@pytest.mark.slow
def test_a_held_frame_in_the_list(snap_compare, app):
    assert snap_compare(app, terminal_size=SIZE, run_before=on_the_held_frame)


@pytest.mark.slow
def test_the_editor_with_a_frame_that_breaks_a_rule(snap_compare, app):
    async def editing(pilot):
        await on_the_held_frame(pilot)
        await pilot.press("e", "ctrl+u")
        await paste(pilot, "rr1-31--0--0-ss1")
        await pilot.press("enter")  # asks before sending it
        await steady(pilot)

    assert snap_compare(app, terminal_size=SIZE, run_before=editing)


@pytest.mark.slow
def test_the_inject_dialog(snap_compare, app):
    async def injecting(pilot):
        await loaded(pilot)
        await settled(pilot)
        await pilot.press("I")
        await paste(pilot, "servo 3 1500")
        await steady(pilot)

    assert snap_compare(app, terminal_size=SIZE, run_before=injecting)


@pytest.mark.slow
def test_the_faults_pane_with_two_faults(snap_compare, app, controller):
    controller.add_fault("delay:200ms dir:s2c jitter:50ms", name="slow-server")
    lossy = controller.add_fault("drop dir:s2c kind:response every:2")
    lossy.hits = 7
    controller.enable_fault("slow-server", False)

    async def faults(pilot):
        await loaded(pilot)
        await settled(pilot)
        await pilot.press("f")
        await pilot.pause()

    assert snap_compare(app, terminal_size=SIZE, run_before=faults)
