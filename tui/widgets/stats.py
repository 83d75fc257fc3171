"""Live statistics: frames per second by direction, latency percentiles, and a
small plot of each sensor and servo channel's value over time.

Everything shown comes from the model's summaries (bounded in size whatever
the traffic: per-second counts, latency buckets, down-sampled series), and is
redrawn on a slow timer, not per frame.  One plot widget per channel seen, at
most 24 sensors and 24 servos.
"""

from __future__ import annotations

from rich.text import Text
from textual.app import ComposeResult
from textual.containers import Horizontal, Vertical, VerticalScroll
from textual.widgets import Label, Sparkline, Static
from whiztap.analyzer.protocol.stats import LatencyStats
from whiztap.tui.data.model import TrafficModel
from whiztap.tui.widgets.detail import latency_text

LIVE_WINDOW_S = 60  # live: the last minute of frames per second
PERCENTILES = (50, 95, 99)
SAME_NS = 1_000_000  # latencies closer than this are the same: the proxy's own hop, not a change of timing


class ChannelPlot(Horizontal):
    """One channel: its name, its values over time, and the latest value.

    Its parts are made here, not found by a query: a plot is mounted while
    the pane is shown, and until Textual has composed it a query finds
    nothing (``s`` pressed twice at once updated a plot in that gap)."""

    DEFAULT_CSS = """
    ChannelPlot { height: 1; }
    ChannelPlot > .name { width: 10; color: $text-muted; }
    ChannelPlot > Sparkline { width: 1fr; }
    ChannelPlot > .value { width: 18; text-align: right; }
    """

    def __init__(self, kind: str, channel: int) -> None:
        super().__init__(id=f"plot-{kind}-{channel}")
        self.kind, self.channel = kind, channel
        self.sparkline = Sparkline([], summary_function=lambda values: sum(values) / len(values))
        self.value = Label("", classes="value")

    def compose(self) -> ComposeResult:
        yield Label(f"{self.kind} {self.channel}", classes="name")
        yield self.sparkline
        yield self.value

    def show(self, points: list[tuple[int, float]]) -> None:
        values = [v for _, v in points]
        self.sparkline.data = values
        if values:
            self.value.update(f"{values[-1]:g} ({min(values):g}-{max(values):g})")


def _rows(out: Text, latencies: dict[str, LatencyStats]) -> None:
    for title, stats in latencies.items():
        out.append(f"{title}", style="bold")
        out.append(f"  {stats.count:,} answered\n", style="dim")
        cells = [f"p{p} {latency_text(stats.percentile(p))}" for p in PERCENTILES]
        out.append("  " + "  ".join(cells + [f"max {latency_text(stats.max)}"]) + "\n")
    if not latencies:
        out.append("  no answered request yet\n", style="dim")


def _differ(server: dict[str, LatencyStats], client: dict[str, LatencyStats]) -> bool:
    """The proxy changed the timing: a request kind's latencies differ between
    the sides by more than ``SAME_NS`` at a percentile shown (or one side has
    answers the other has not)."""
    if server.keys() != client.keys():
        return True
    for title, s in server.items():
        c = client[title]
        if s.count != c.count or abs(s.max - c.max) > SAME_NS:
            return True
        if any(abs(s.percentile(p) - c.percentile(p)) > SAME_NS for p in PERCENTILES):
            return True
    return False


class StatsPane(VerticalScroll):
    DEFAULT_CSS = """
    StatsPane { padding: 0 1; }
    StatsPane .title { text-style: bold; margin-top: 1; }
    StatsPane .rate { height: 1; }
    StatsPane .rate > Label { width: 10; color: $text-muted; }
    StatsPane .rate > Sparkline { width: 1fr; }
    StatsPane .rate > .now { width: 18; text-align: right; }
    StatsPane #rate-c2s > Sparkline > .sparkline--max-color { color: $success; }
    StatsPane #rate-s2c > Sparkline > .sparkline--max-color { color: $warning; }
    """

    def __init__(self, model: TrafficModel, live: bool, *, id: str | None = None) -> None:
        super().__init__(id=id)
        self.model = model
        self.live = live
        # the parts the timer updates, made here as ChannelPlot's are
        self.rate_title = Static("Frames per second", classes="title", id="rate-title")
        self.rates = {direction: (Sparkline([]), Label("", classes="now")) for direction in ("c2s", "s2c")}
        self.latency = Static("no answered request yet", id="latency")
        self.plots = Vertical(id="plots")
        self.plot_of: dict[tuple[str, int], ChannelPlot] = {}

    def compose(self) -> ComposeResult:
        yield self.rate_title
        for direction, label in (("c2s", "client →"), ("s2c", "server ←")):
            sparkline, now = self.rates[direction]
            with Horizontal(classes="rate", id=f"rate-{direction}"):
                yield Label(label)
                yield sparkline
                yield now
        yield Static("Latency", classes="title")
        yield self.latency
        yield Static("Channels (sensor value, servo position)", classes="title")
        yield self.plots

    def update_stats(self) -> None:
        window = LIVE_WINDOW_S if self.live else None
        c2s, s2c = self.model.store.rate_series(window)
        span = f"last {len(c2s)} s" if self.live else f"over the recording's {self.model.duration_s:.3f} s"
        self.rate_title.update(f"Frames per second ({span})")
        for direction, series in (("c2s", c2s), ("s2c", s2c)):
            sparkline, now = self.rates[direction]
            sparkline.data = series
            peak = max(series, default=0)
            now.update(f"{series[-1] if series else 0:,}/s (max {peak:,})")
        self.latency.update(self._latency_table())
        self._plots()

    def _latency_table(self) -> Text:
        """Two lines per request kind: narrow enough for the side pane.  In the
        middle, where the proxy changed the timing, the server's latency (from
        the request it received to the answer it sent) and the client's (from
        the request it sent to the answer it got), each labelled."""
        server, client = self.model.both_latencies()
        if not server and not client:
            return Text("no answered request yet", style="dim")
        out = Text()
        if client and _differ(server, client):
            out.append("the server's (what it received → what it sent)\n", style="italic")
            _rows(out, server)
            out.append("the client's (what it sent → what it got)\n", style="italic")
            _rows(out, client)
        else:
            _rows(out, server)
        out.rstrip()
        return out

    def _plots(self) -> None:
        for key, points in self.model.channel_values().items():
            plot = self.plot_of.get(key)
            if plot is None:
                plot = self.plot_of[key] = ChannelPlot(*key)
                self.plots.mount(plot)
            plot.show(points)
