"""The whiztap TUI: connections, the frame list, the selected frame, statistics.

The app owns no traffic: a source feeds the model from a worker thread, and a
tick (``TICK_S``) lets the frame list take in new rows, so the screen costs
the same at ten frames a second or ten thousand.  Filtering runs in another
worker, replaced (``exclusive``) whenever the filter changes.
"""

from __future__ import annotations

import gc
import os
import sys
import threading
import time
from collections import deque
from typing import Any

from rich.text import Text
from textual import on, work
from textual.app import App, ComposeResult
from textual.binding import Binding
from textual.containers import Horizontal
from textual.content import Content
from textual.message import Message
from textual.widgets import Footer, Header, Input, Static, TabbedContent, TabPane
from textual.worker import get_current_worker
from whiztap.analyzer.analysis.item_filter import FILTER_HELP, FilterSyntaxError, ItemFilter, parse_filter
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.protocol.text import printable
from whiztap.tui.data.controls import Controls, HeldKey
from whiztap.tui.data.model import TrafficModel, verdict_text
from whiztap.tui.data.sources import LiveSource, Source, SourceError
from whiztap.tui.data.view import FrameView, with_connection
from whiztap.tui.middle.editor import EditorScreen
from whiztap.tui.middle.faults_pane import FaultsPane
from whiztap.tui.middle.inject import InjectScreen, closed_to_injection, target_connection
from whiztap.tui.middle.intercept_bar import InterceptBar
from whiztap.tui.screens.help import HelpScreen
from whiztap.tui.widgets.connections import ConnectionsPane
from whiztap.tui.widgets.detail import DetailPane
from whiztap.tui.widgets.filter_bar import FilterBar
from whiztap.tui.widgets.frame_list import FrameList
from whiztap.tui.widgets.held import EditHeld
from whiztap.tui.widgets.stats import StatsPane
from whiztap.tui.widgets.virtual_list import VirtualList

TICK_S = 0.1  # new frames show within this (plus the time to decode them)
LOADING_TICK_S = 0.5  # while a recording loads: each look repaints the screen, which slows the loading
FOLLOWING_DETAIL_S = 0.5  # while following, the detail pane shows the newest frame this often
SLOW_TICK_S = 1.0  # connections and statistics
MIDDLE_ACTIONS = frozenset({"intercept", "inject", "faults"})  # keys of the live proxy in the middle
JUDGE_IDLE_S = 0.05  # a filter worker with nothing to judge looks again after this
FEED_SWITCH_S = 0.0005  # the interpreter's switch interval while a source feeds the model


class Fed(Message):
    """The source has no more traffic (the file ended, the proxy stopped)."""

    def __init__(self, note: str) -> None:
        super().__init__()
        self.note = note


class WhiztapApp(App):
    TITLE = "whiztap"
    CSS = """
    #main { height: 1fr; }
    #frames { width: 3fr; min-width: 60; }
    #side { width: 2fr; min-width: 44; }
    #side.hidden { display: none; }
    #status { height: 1; background: $panel; color: $text-muted; padding: 0 1; }
    """
    BINDINGS = [
        Binding("q", "quit", "Quit"),
        Binding("question_mark", "help", "Help"),
        Binding("slash", "filter", "Filter"),
        Binding("c", "connections", "Connections"),
        Binding("d", "pane('detail')", "Detail"),
        Binding("s", "pane('stats')", "Stats"),
        Binding("z", "wide", "Wide list"),
        Binding("r", "replay", "Replay"),
        Binding("b", "bisect", "Bisect", show=False),
        Binding("i", "intercept", "Intercept"),
        Binding("I", "inject", "Inject"),
        Binding("f", "faults", "Faults"),
        Binding("escape", "leave", show=False),
    ]

    def __init__(self, source: Source, *, checksum_rule: str = DEFAULT_CHECKSUM_RULE,
                 limits: Limits = Limits(), quit_after: float | None = None) -> None:
        super().__init__()
        self.source = source
        self.live = source.live
        self.model = TrafficModel(getattr(source, "path", ""), checksum_rule, source.redact_passwords, limits)
        self.quit_after = quit_after
        self.controls = Controls(source)  # the live proxy's Controller: held frames, faults, injection
        self.error: str | None = None  # why the app ended early (the CLI prints it)
        self.failure: BaseException | None = None  # what broke the app, unexpectedly (the CLI says so)
        self.fed = False
        self.lags: deque[int] = deque(maxlen=10_000)  # live, per tick: ns the oldest new frame waited to show
        self.filter_text = ""
        self.chosen_conn: int | None = None
        self._stop = threading.Event()
        self._quitting = False
        self._last_sync = 0.0
        self._detail_due: int | HeldKey | None = None  # the frame the detail pane should show
        self._detail_at = 0.0

    # -- layout ------------------------------------------------------------------------------

    def compose(self) -> ComposeResult:
        """The main screen; its widgets are kept as attributes, since ``query_one``
        would look in whichever screen (help, replay) is on top."""
        store = self.model.store
        self.connections = ConnectionsPane(id="connections")
        self.frames = FrameList(store, FrameView(store), live=self.live, controls=self.controls, id="frames")
        self.tabs = TabbedContent(id="side")
        self.detail = DetailPane(store, self.controls, id="detail-pane")
        self.faults = FaultsPane(self.controls, id="faults-pane")
        self.intercept_bar = InterceptBar(self.controls, id="intercept")
        self.stats = StatsPane(self.model, self.live, id="stats-pane")
        self.filter_bar = FilterBar(placeholder=FILTER_HELP, id="filter")
        self.status = Static("", id="status")
        yield Header(show_clock=False)
        yield self.connections
        with Horizontal(id="main"):
            yield self.frames
            with self.tabs:
                with TabPane("Detail", id="detail"):
                    yield self.detail
                with TabPane("Stats", id="stats"):
                    yield self.stats
                if self.controls.available:
                    with TabPane("Faults", id="faults"):
                        yield self.faults
        yield self.filter_bar
        yield self.intercept_bar
        yield self.status
        yield Footer()

    def format_title(self, title: str, sub_title: str) -> Content:
        """Titles name files (and replay screens, their outputs): shown, never obeyed."""
        return super().format_title(printable(title), printable(sub_title))

    def on_mount(self) -> None:
        self.sub_title = self.source.title
        frames = self.frames
        frames.border_title = "Frames"
        frames.focus()
        if self.live:
            frames.tail = True
        if isinstance(self.source, LiveSource):
            self.source.on_failure = self._live_failed
            self.source.on_warning = self._live_warning
            self._start_live(self.source)
        else:
            self._feed()
        # Move what the app holds at start into the collector's permanent
        # generation: while traffic streams, full collections then walk only
        # what came since, not every widget and style (as batch commands do,
        # see whiztap.analyzer.analysis.throughput).
        self.call_after_refresh(gc.freeze)
        self.set_interval(TICK_S, self._tick)
        self.set_interval(SLOW_TICK_S, self.refresh_summaries)
        if self.quit_after is not None:
            self.set_timer(self.quit_after, self.action_quit)

    # -- workers -----------------------------------------------------------------------------

    @work(group="live", exit_on_error=False)
    async def _start_live(self, source: LiveSource) -> None:
        try:
            await source.start()
        except SourceError as e:
            self.error = str(e)
            self.exit(return_code=2)
            return
        self.sub_title = self.source.title
        self._feed()

    @work(thread=True, group="feed")
    def _feed(self) -> None:
        """Feed the model.  Meanwhile threads take turns with the interpreter
        every FEED_SWITCH_S instead of every 5 ms: the event loop (the screen,
        and the proxy in live mode) wants it back after every select(), and at
        5 ms a turn a key press took seconds to show while a file loaded."""
        interval = sys.getswitchinterval()
        sys.setswitchinterval(FEED_SWITCH_S)
        try:
            self.source.feed(self.model, self._stop)
        except OSError as e:
            self.source.note = f"reading stopped: {e.strerror or e}"
        finally:
            sys.setswitchinterval(interval)
        if not self._stop.is_set():
            self.post_message(Fed(self.source.note))

    @work(thread=True, exclusive=True, group="filter")
    def _judge(self, view: FrameView) -> None:
        worker = get_current_worker()
        while not worker.is_cancelled:
            view.judge(lambda: worker.is_cancelled)
            if self.fed and view.complete:
                return
            time.sleep(JUDGE_IDLE_S)

    def _live_failed(self, note: str) -> None:
        self.notify(note, severity="error", timeout=10, markup=False)  # names files: never markup

    def _live_warning(self, text: str) -> None:
        """The proxy's warning (a script that raised: its first line and its
        traceback's last), shown once; the proxy and the screen go on."""
        lines = text.splitlines()
        shown = lines[0] if len(lines) < 2 else f"{lines[0]}\n{lines[-1]}"
        self.notify(shown, severity="warning", timeout=10, markup=False)

    # -- ticks -------------------------------------------------------------------------------

    def _tick(self) -> None:
        frames = self.frames
        now = time.monotonic()
        if not self.live and not self.fed and frames.rows >= frames.size.height \
                and now - self._last_sync < LOADING_TICK_S:
            return
        self._last_sync = now
        if self.live and self.sub_title != self.source.title:
            self.sub_title = self.source.title  # a followed recording moved on to its next part
        self.controls.poll()
        before = frames.store_rows
        if frames.take_in():
            self.detail.refresh_frame()
        if self._detail_due != self.detail.frame and now - self._detail_at >= FOLLOWING_DETAIL_S:
            self._show_detail()
        if self.live and frames.store_rows > before:
            # the frame that waited longest to be shown: the first of those new now
            self.lags.append(time.time_ns() - self.model.store.t_end[frames.view[before]])
        if not self.live:
            # Live, the status line changes on the slow tick only: a widget far
            # from the list changing in the same frame makes Textual repaint
            # everything between them.
            self._show_status()

    def refresh_summaries(self) -> None:
        """Connections, statistics and (live) the status line: once a second."""
        if self.live:
            self._show_status()
        self.connections.show(self.model.connections())
        if self.tabs.active == "stats":
            self.stats.update_stats()

    def _show_status(self) -> None:
        store = self.model.store
        frames = self.frames
        parts = [f"{store.count:,} frames", verdict_text(self.model.verdict())]
        progress = self.source.progress
        if progress is not None and not self.fed:
            parts.append(f"loading {progress:.0%}")
        if isinstance(self.source, LiveSource) and self.lags:
            parts.append(f"frames shown within {self.lags[-1] / 1e6:.0f} ms of arrival")
        mirror = self.source.recording.mirror if isinstance(self.source, LiveSource) and self.source.recording else None
        if mirror is not None:  # record --mirror: how the mirror's answers compare, and the latest difference
            parts.append(mirror.view.text() + (f"; latest {mirror.view.latest[-1]}" if mirror.view.latest else ""))
        view = frames.view
        if not view.all:
            where = "" if view.complete else f" (filtering {view.judged / max(store.count, 1):.0%})"
            parts.append(f"filter: {self._filter_label()}{where} → {len(view):,} shown")
        self.status.update(Text(" · ".join(parts)), layout=False)  # the filter's words: never markup

    def _filter_label(self) -> str:
        words = [self.filter_text] if self.filter_text else []
        if self.chosen_conn is not None:
            words.append(f"conn #{self.chosen_conn} (pane)")
        return " ".join(words)

    # -- events ------------------------------------------------------------------------------

    @on(Fed)
    def _on_fed(self, message: Fed) -> None:
        self.fed = True
        self.sub_title = self.source.title
        if message.note:
            self.notify(message.note, severity="warning", timeout=8, markup=False)
        self._tick()
        self.refresh_summaries()

    @on(VirtualList.Moved, "#frames")
    def _on_moved(self, message: VirtualList.Moved) -> None:
        """Show the frame under the cursor; while following a fast stream, only
        now and then (laying out a detail pane costs more than a tick)."""
        key = message.key
        self._detail_due = key if isinstance(key, (int, HeldKey)) else None  # the frame list's keys
        if not self.frames.tail or time.monotonic() - self._detail_at >= FOLLOWING_DETAIL_S:
            self._show_detail()

    def _show_detail(self) -> None:
        self._detail_at = time.monotonic()
        self.detail.show(self._detail_due)

    @on(ConnectionsPane.Chosen)
    def _on_chosen(self, message: ConnectionsPane.Chosen) -> None:
        self.chosen_conn = message.conn
        self._apply_filter()
        self.frames.focus()

    @on(Input.Submitted, "#filter")
    def _on_filter(self, message: Input.Submitted) -> None:
        """Words that do not parse are refused on the bar; the filter in force
        stays, and the status line goes on naming it."""
        text = message.value.strip()
        try:
            parse_filter(text)
        except FilterSyntaxError as e:
            self.filter_bar.refuse(f"not applied: {e}; in force: {self.filter_text or 'nothing'}")
            return
        self.filter_text = text
        self._apply_filter()
        self.frames.focus()
        if not text:
            self.filter_bar.remove_class("shown")

    def _apply_filter(self) -> None:
        """The list through the filter in force (which parsed) and the connection chosen."""
        item_filter = with_connection(parse_filter(self.filter_text), self.chosen_conn)
        view = FrameView(self.model.store, item_filter)
        self.frames.set_view(view)
        if item_filter != ItemFilter():
            self._judge(view)
        else:
            self.workers.cancel_group(self, "filter")
        self._show_status()

    # -- actions -----------------------------------------------------------------------------

    MAIN_SCREEN_ACTIONS = frozenset({"filter", "connections", "pane", "wide", "replay", "leave", "bisect"})

    def check_action(self, action: str, parameters: tuple[object, ...]) -> bool | None:
        """The main screen's keys do nothing while another screen (help, replay) is on top."""
        if action in MIDDLE_ACTIONS:
            return self.controls.available and len(self.screen_stack) == 1  # live, in the middle only
        return action not in self.MAIN_SCREEN_ACTIONS or len(self.screen_stack) <= 1

    def action_help(self) -> None:
        self.push_screen(HelpScreen())

    def action_filter(self) -> None:
        bar = self.filter_bar
        bar.add_class("shown")
        bar.focus()

    def action_leave(self) -> None:
        bar = self.filter_bar
        if bar.has_focus:
            bar.value = self.filter_text
            if not self.filter_text:
                bar.remove_class("shown")
        self.frames.focus()

    def action_connections(self) -> None:
        self.connections.focus()

    def action_wide(self) -> None:
        """Hide or show the side pane: the whole width for the frame list."""
        self.tabs.toggle_class("hidden")

    def action_pane(self, pane: str) -> None:
        self.tabs.remove_class("hidden")
        self.tabs.active = pane
        if pane == "stats":
            self.stats.update_stats()

    def action_replay(self) -> None:
        from whiztap.tui.screens.replay_screen import open_replay

        open_replay(self)

    def action_bisect(self) -> None:
        """The first frame with a violation of a rule, or where two connections part (screens/bisect.py)."""
        from whiztap.tui.screens.bisect import open_bisect

        open_bisect(self, self.model.store, self.frames, self.fed)

    def action_intercept(self) -> None:
        self.intercept_bar.open()

    def action_inject(self) -> None:
        """A frame into the selected frame's connection (or the pane's choice, or the only one open)."""
        if self.controls.controller is None:
            return
        conn = target_connection(self.frames, self.chosen_conn, self.controls)
        if conn is None:
            self.notify("which connection? select one of its frames, or choose it in the connections pane (c)",
                        severity="warning", timeout=4)
            return
        closed = closed_to_injection(self.controls, conn)
        if closed:
            self.notify(closed, severity="warning", timeout=4, markup=False)
            return
        self.push_screen(InjectScreen(self.controls, conn))

    def on_edit_held(self, message: EditHeld) -> None:
        """``e`` on a held frame in the list: edit it, then let it go (middle/editor.py)."""
        self.push_screen(EditorScreen(self.controls, message.held))

    def action_faults(self) -> None:
        self.action_pane("faults")
        self.faults.focus_table()

    async def action_quit(self) -> None:
        """Quit; a live recording is finished (connections closed, file indexed) first."""
        if self._quitting:
            return
        self._quitting = True
        try:
            unfinished = self._unfinished_recording()
            if unfinished is not None:
                self.notify("finishing the recording…", timeout=30)
                await unfinished.stop()
        finally:
            self._stop.set()
            self.exit()

    def _unfinished_recording(self) -> LiveSource | None:
        """The live source whose recording is still being written, if there is one."""
        source = self.source
        if isinstance(source, LiveSource) and source.recording is not None and not source.stopped.is_set():
            return source
        return None

    async def run_async(self, **options: Any) -> Any:
        """Run the app (``App.run`` comes here); whatever ended it, ``q`` or
        an unexpected failure, a live recording is finished before this
        returns, on the loop the proxy runs on: a failure of the screen
        closes the connections as ``q`` does and never leaves the file to
        the writer's own end."""
        try:
            return await super().run_async(**options)
        finally:
            unfinished = self._unfinished_recording()
            if unfinished is not None:
                await unfinished.stop()

    def _handle_exception(self, error: Exception) -> None:
        """An unexpected failure (Textual ends the app on one): kept for the
        command, which says it in one line with where the recording is.
        Textual's traceback shows each frame's local variables, which may
        hold what the screen masks (a password): printed only with
        WHIZTAP_DEBUG, as the root command prints tracebacks."""
        if self.failure is None:
            self.failure = error
        super()._handle_exception(error)
        if not os.environ.get("WHIZTAP_DEBUG"):
            self._exit_renderables.clear()

    def on_unmount(self) -> None:
        self._stop.set()
