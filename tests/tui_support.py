"""Helpers for the TUI tests: waiting on the app without timing assertions."""

from __future__ import annotations

import asyncio
from collections.abc import Callable
from pathlib import Path

from whiztap.sniffer.mitm.controller import Controller
from whiztap.tui.data.sources import FileSource

ROOT = Path(__file__).parent.parent
SAMPLES = ROOT / "samples"
WAIT = 20.0  # a generous bound on anything awaited; never a timing assertion
SIZE = (130, 40)


async def until(pilot, condition: Callable[[], bool], what: str = "condition") -> None:
    """Let the app run until ``condition()`` holds (fail after WAIT seconds)."""
    loop = asyncio.get_running_loop()
    deadline = loop.time() + WAIT
    while not condition():
        if loop.time() > deadline:
            raise AssertionError(f"gave up waiting for {what}")
        await pilot.pause(0.02)


async def paste(pilot, text: str) -> None:
    """Paste ``text`` into the focused widget, as a terminal's bracketed paste
    does: one event.  Pilot spends about 0.1 s on each key it presses (it
    waits for the app to idle three times), so the tests press the keys a
    test is about and paste the rest."""
    from textual import events

    pilot.app.post_message(events.Paste(text))
    await pilot.pause()


async def loaded(pilot) -> None:
    """Until the recording is read and the list shows all of it."""
    app = pilot.app
    await until(pilot, lambda: app.fed and app.frames.store_rows == len(app.frames.view) and app.frames.view.complete,
                "the recording to load")
    await pilot.pause()


async def settled(pilot) -> None:
    """Until the slow panes caught up: every connection in its table, every plot drawn."""
    app = pilot.app
    app.refresh_summaries()
    await until(pilot, lambda: len(app.connections.rows) == len(app.model.connections()) + 1, "the connections")
    if app.tabs.active == "stats":
        from textual.widgets import Sparkline

        wanted = len(app.model.channel_values())
        await until(pilot, lambda: len(app.stats.query("ChannelPlot")) == wanted and all(
            plot.query_one(Sparkline).data for plot in app.stats.query("ChannelPlot")), "the plots")
    await pilot.pause()


def frames_shown(app) -> list[int]:
    """The frame ids of the list's rows."""
    view = app.frames.view
    return [view[row] for row in range(app.frames.rows)]


class IdleShell:
    """A connection's shell that carries out nothing: a Controller's core
    (driven by no proxy, its clock the test's) whose lanes write nowhere."""

    client_addr = "127.0.0.1:40000"

    def run(self, commands: list) -> None:
        pass


class BesideAController(FileSource):
    """A fixed recording, with a Controller beside it as the live source has one."""

    def __init__(self, path: str, controller: Controller) -> None:
        super().__init__(path)
        self.controller = controller
