"""The TUI never dies on keys: random key sequences, pressed as a person
would and faster than Textual can lay out (a burst of keys posted at once,
as a terminal delivers what was typed ahead), on a recording and on live
traffic through the real proxy, while dialogs open and close.

The keys are every binding of the app, its panes and its screens, read from
the classes (a new binding is pressed without a change here), and a few
pasted texts that get somewhere: a filter, an intercept filter that holds
frames, a frame to inject, a fault, a bisect query."""

from __future__ import annotations

import contextlib
import importlib
import pkgutil
import tempfile
from pathlib import Path
from unittest import mock

import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st
from textual import events
from textual.app import App
from textual.screen import Screen

import whiztap.tui
from whiztap.analyzer.recording.scan import read_metadata
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.tui.screens import replay_screen
from whiztap.tui.app import WhiztapApp
from whiztap.tui.demo import DemoRig
from whiztap.tui.data.sources import FileSource, LiveSource

from tests.tui_support import SAMPLES, SIZE, loaded, until


def bound_classes() -> set[type]:
    """Every class of the TUI that declares keys, and Textual's app and screen
    (Tab, Ctrl+Q, Ctrl+C, the command palette's Ctrl+P)."""
    found: set[type] = {App, Screen}
    for info in pkgutil.walk_packages(whiztap.tui.__path__, "whiztap.tui."):
        module = importlib.import_module(info.name)
        found |= {cls for cls in vars(module).values()
                  if isinstance(cls, type) and cls.__module__ == module.__name__ and "BINDINGS" in vars(cls)}
    return found


KEYS = sorted({key.strip() for cls in bound_classes() for binding in cls.BINDINGS
               for key in (binding.key if hasattr(binding, "key") else binding[0]).split(",")}
              | {App.COMMAND_PALETTE_BINDING, "enter", "backspace", "shift+tab", "left", "right", "1", "2", ":"})
CHARACTERS = {"question_mark": "?", "slash": "/", "space": " ", "colon": ":", "enter": "\r", "tab": "\t",
              "escape": "\x1b", "backspace": "\x7f"}
TEXTS = ("sensor 12", "servo 3 1500", "rr1-31--0--2-ss1", "kind:command ch:12", "dir:sideways", "violations",
         "drop dir:s2c kind:response every:2", "delay:50ms dir:c2s", "PW-PAIR", "error", "1 2", "")
# a key pressed once or a few times in a row (a double press: "s s"), fast or waiting for the app
STEP = st.one_of(st.tuples(st.sampled_from(KEYS), st.integers(1, 3), st.booleans()),
                 st.tuples(st.sampled_from(TEXTS).map(lambda text: f"paste:{text}"), st.just(1), st.just(True)))
SEQUENCE = st.lists(STEP, min_size=1, max_size=14)


def _key(key: str) -> events.Key:
    return events.Key(key, CHARACTERS.get(key, key if len(key) == 1 else None))


async def play(pilot, steps: list[tuple[str, int, bool]]) -> None:
    """Each step a key pressed ``times`` or a paste; a fast one is posted
    without waiting (the next comes before the app has dealt with it), a slow
    one waits for the app to idle, as Pilot's press does."""
    app = pilot.app
    for key, times, fast in steps:
        if not app.is_running:
            return
        if key.startswith("paste:"):
            app.post_message(events.Paste(key.removeprefix("paste:")))
        elif fast:
            for _ in range(times):
                app.post_message(_key(key))
        else:
            await pilot.press(*[key] * times)
    if app.is_running:  # the timers' turn: a tick, and the slow one's refresh (once a second) at once
        await pilot.pause(0.1)
    if app.is_running:
        app.refresh_summaries()
        await pilot.pause()


# A failing sequence is short enough to read as it is: no shrinking, which
# would start an app (and, live, a proxy) hundreds of times over.
KEY_SETTINGS = settings(max_examples=16, deadline=None, phases=(Phase.explicit, Phase.reuse, Phase.generate),
                        suppress_health_check=[HealthCheck.too_slow])


@pytest.mark.slow
@KEY_SETTINGS
@example(steps=[("s", 2, True)])  # 's' twice at once: the plots' first update raced their mounting
@given(steps=SEQUENCE)
async def test_random_keys_on_a_recording_never_raise(steps):
    async with Simulator(mode="winsock", password="progwhiz", seed=1) as sim:  # r, F5: a real replay target
        with mock.patch.object(replay_screen, "DEFAULT_TARGET", f"127.0.0.1:{sim.port}"), \
                tempfile.TemporaryDirectory() as folder, contextlib.chdir(folder):  # Ctrl+P's screenshot goes here
            app = WhiztapApp(FileSource(str(SAMPLES / "violations.mcap")))
            async with app.run_test(size=SIZE) as pilot:
                await loaded(pilot)
                await play(pilot, steps)


@pytest.mark.slow
@settings(KEY_SETTINGS, max_examples=8)
@given(steps=SEQUENCE, intercept=st.sampled_from(("", "kind:command ch:12", "dir:s2c")))
async def test_random_keys_on_live_traffic_through_the_proxy_never_raise(steps, intercept):
    with tempfile.TemporaryDirectory() as folder, contextlib.chdir(folder):
        output = Path(folder) / "live.mcap"
        app = WhiztapApp(LiveSource(DemoRig(str(output)), "demo"))
        async with app.run_test(size=SIZE) as pilot:
            await until(pilot, lambda: app.model.store.count >= 10, "the demo's first frames")
            if intercept:
                app.source.controller.set_intercept(intercept)  # frames held for a, x, e and A
            await play(pilot, steps)
            if app.is_running:
                await app.action_quit()
            await until(pilot, lambda: not app.is_running, "the app to quit")
        assert read_metadata(str(output))["source"] == "proxy"  # the recording was finished, whatever the keys did
