"""The TUI with a million frames and with 10,000 frames a second.

- First screen: a fresh process runs ``whiztap tui`` on the cached one-million-
  frame recording (bench_analyze's pipelined file) with Textual's headless
  driver, and reports when the frame list first painted rows, counted from
  before the process was started (interpreter, imports and all).
- Scrolling to the end: End pressed while the file is still loading (the list
  jumps to what is loaded and follows it), and again once everything is
  loaded; the time until the last row is painted.
- Memory: what the frame store's columns hold per frame, and the process's
  resident size grown per frame from the first screen to the full load.
- Live: the proxy inside the app, in front of ``whiztap sim`` (another
  process), with a pipelined client (a third process) sending 5,000 Sensor
  Requests a second, i.e. 10,000 frames a second both ways.  The delay is,
  at each tick that shows new frames, how long the oldest of them waited
  since it arrived at the proxy; the backlog is what the proxy had passed on
  and the model had not taken yet.
- Live while frames are held: the same, with an intercept filter (``ch:20``)
  that the load's frames all go through and a second connection's
  ``HELD`` Sensor Requests on channel 20 match, so that many frames wait at
  the proxy (shown after the list's rows, their wait counted each tick)
  for the whole run; the same delays, p99 first.
"""

from __future__ import annotations

import asyncio
import json
import re
import resource
import subprocess
import sys
import time
from pathlib import Path

FRAMES = 1_000_000
LIVE_RATE = 5_000  # requests a second; as many answers come back
LIVE_SECONDS = 6.0
HELD = 50  # frames the intercept filter holds during the live run with interception
HELD_FILTER = "ch:20"  # the load asks for channel 12: only the second connection's frames match
_PAINTED: dict[int, float] = {}  # frame id -> when a row showing it was first painted
_CURSOR: dict[int, float] = {}  # frame id -> when it was first painted under the cursor


def _instrument() -> None:
    """Note when rows are painted (benchmark only: wraps the list's render_line,
    which runs for every line drawn, cached strip or not)."""
    from whiztap.tui.widgets.frame_list import FrameList

    render_line = FrameList.render_line

    def timed(self, y):
        strip = render_line(self, y)
        row = self.scroll_offset.y + y
        if row < self.rows:
            now = time.perf_counter()
            _PAINTED.setdefault(self.view[row], now)
            if row == self.cursor:
                _CURSOR.setdefault(self.view[row], now)
        return strip

    FrameList.render_line = timed


def _rss_kib() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * resource.getpagesize() // 1024


KEY_WAIT_S = 120.0  # a paint that has not come by then is reported as missing, not waited for


async def _key(app, key: str, painted: dict, frame: int, or_later: bool = False) -> float | None:
    """Seconds from a key reaching the app to ``frame`` being painted (with
    ``or_later``, any later frame: End while loading lands wherever the last
    row is by then, which on a slow machine can be thousands of rows on).  The
    key is posted as the terminal driver posts it: Pilot.press first waits for
    the app to be idle, which a loading app never is.  None if nothing came."""
    from textual import events

    painted.clear()
    start = time.perf_counter()
    app.post_message(events.Key(key, None))
    while True:
        if frame in painted:
            return painted[frame] - start
        if or_later and painted and max(painted) > frame:
            return min(t for f, t in painted.items() if f > frame) - start
        if time.perf_counter() - start > KEY_WAIT_S:
            return None
        await asyncio.sleep(0.001)


async def _browse(path: str, started: float) -> dict:
    """In the fresh process: open the recording headless and time what a user sees."""
    _instrument()
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.data.sources import FileSource

    app = WhiztapApp(FileSource(path))
    out: dict = {}
    async with app.run_test(size=(160, 50)):
        frames = app.frames
        while not _PAINTED:
            await asyncio.sleep(0.001)
        out["first_screen_s"] = min(_PAINTED.values()) - started
        out["rss_first_kib"] = _rss_kib()
        out["frames_at_first_screen"] = app.model.store.count
        await asyncio.sleep(0.3)
        moves = [m for _ in range(20) if (m := await _key(app, "j", _CURSOR, frames.view[frames.cursor + 1]))
                 is not None]
        out["j_while_loading_s"] = sorted(moves)[len(moves) // 2] if moves else None
        out["end_while_loading_s"] = await _key(app, "end", _PAINTED, frames.view[frames.rows - 1], or_later=True)
        out["frames_when_end_pressed"] = frames.rows
        while not app.fed:
            await asyncio.sleep(0.05)
        out["load_s"] = time.perf_counter() - started
        await _key(app, "home", _PAINTED, 0)
        await asyncio.sleep(0.2)
        out["end_loaded_s"] = await _key(app, "end", _PAINTED, app.model.store.count - 1)
        store = app.model.store
        out["frames"] = store.count
        out["store_bytes_per_frame"] = store.nbytes() / store.count
        out["rss_loaded_kib"] = _rss_kib()
    return out


def _ms(seconds: float | None) -> str:
    return f"{seconds * 1e3:.0f} ms" if seconds is not None else f"(nothing painted within {KEY_WAIT_S:g} s)"


def _first_screen(path: str) -> dict:
    # perf_counter is CLOCK_MONOTONIC on Linux, the same in every process: the
    # child measures from this moment, before it was started.
    code = (f"import asyncio, json; from benchmarks.bench_tui import _browse; "
            f"print(json.dumps(asyncio.run(_browse({path!r}, {time.perf_counter()!r}))))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


# -- live ---------------------------------------------------------------------------------------


async def _drive(port: int, rate: int, seconds: float) -> None:
    """The load: pipelined Sensor Requests at ``rate`` a second, answers read and dropped."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)

    async def drain() -> None:
        while await reader.read(1 << 16):
            pass

    draining = asyncio.create_task(drain())
    batch = 50
    frame = b"rr1-12--0--0-ss1"
    writer.write(b"rr1-24--0--0-ss1")
    start = time.perf_counter()
    sent = 0
    while time.perf_counter() - start < seconds:
        writer.write(frame * batch)
        sent += batch
        await writer.drain()
        ahead = sent / rate - (time.perf_counter() - start)
        if ahead > 0:
            await asyncio.sleep(ahead)
    await asyncio.sleep(0.5)
    writer.close()
    draining.cancel()
    print(sent)


async def _hold(app, port: int, held: int) -> asyncio.StreamWriter:
    """Intercept ``HELD_FILTER`` and have a second client send ``held`` frames it matches."""
    controller = app.source.controller
    controller.set_intercept(HELD_FILTER)
    _, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(b"rr1-20--0--0-ss1" * held)
    await writer.drain()
    while len(controller.held.frames) < held:
        await asyncio.sleep(0.01)
    return writer


async def _live(tmp: str, held: int = 0) -> dict:
    from whiztap.sniffer.record.record_run import RecordSettings
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.data.sources import LiveSource, ProxyRig

    whiztap = str(Path(sys.executable).with_name("whiztap"))
    sim = subprocess.Popen([whiztap, "sim", "--mode", "vpn", "--port", "0", "-q"], stdout=subprocess.PIPE, text=True)
    try:
        sim_port = int(re.search(r"listening on \S+:(\d+)", sim.stdout.readline()).group(1))
        settings = RecordSettings(("127.0.0.1", 0), ("127.0.0.1", sim_port), f"{tmp}/live.mcap", quiet=True)
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=(160, 50)) as pilot:
            while app.source.recording is None or app.source.recording.proxy is None:
                await pilot.pause(0.05)
            port = app.source.recording.proxy.port
            holder = await _hold(app, port, held) if held else None
            backlog = 0
            driver = await asyncio.create_subprocess_exec(
                sys.executable, "-c", f"import asyncio; from benchmarks.bench_tui import _drive; "
                                      f"asyncio.run(_drive({port}, {LIVE_RATE}, {LIVE_SECONDS}))",
                stdout=asyncio.subprocess.PIPE)
            app.lags.clear()
            while driver.returncode is None:
                backlog = max(backlog, app.source.backlog)
                try:
                    await asyncio.wait_for(driver.wait(), 0.05)
                except TimeoutError:
                    pass
            sent = int((await driver.stdout.read()).split()[-1])
            while app.source.backlog:
                await pilot.pause(0.05)
            await pilot.pause(0.5)
            lags = sorted(app.lags)
            frames = app.model.store.count
            still_held = len(app.source.controller.held.frames)
            if holder is not None:
                app.source.controller.release_all()
                holder.close()
            await pilot.press("q")
            while app.is_running:
                await pilot.pause(0.05)
    finally:
        sim.terminate()
        sim.wait()
    def pick(q: float) -> float:
        return lags[min(len(lags) - 1, int(q * len(lags)))] / 1e6

    return {"sent_requests": sent, "frames_shown": frames, "lag_p50_ms": pick(0.5), "lag_p99_ms": pick(0.99),
            "lag_max_ms": lags[-1] / 1e6, "backlog_max": backlog, "ticks": len(lags), "held": still_held}


def main() -> None:
    import tempfile

    from benchmarks.bench_analyze import READ, recording

    print("== tui")
    path = str(recording("pipelined", FRAMES, READ))
    r = _first_screen(path)
    print(f"first screen of {r['frames']:,} frames (fresh process, headless): {r['first_screen_s']:.2f} s "
          f"({r['frames_at_first_screen']:,} frames loaded by then); all loaded after {r['load_s']:.1f} s")
    print(f"while loading: j moves the cursor in {_ms(r['j_while_loading_s'])} (median of 20); "
          f"End paints the last row loaded ({r['frames_when_end_pressed']:,}) in {_ms(r['end_while_loading_s'])}")
    print(f"once loaded: End paints the last of {r['frames']:,} rows in {_ms(r['end_loaded_s'])}")
    grown = (r["rss_loaded_kib"] - r["rss_first_kib"]) * 1024 / (r["frames"] - r["frames_at_first_screen"])
    print(f"memory held per frame: store {r['store_bytes_per_frame']:.0f} B; "
          f"process grew {grown:.0f} B/frame from first screen to full load")
    with tempfile.TemporaryDirectory() as tmp:
        live = asyncio.run(_live(tmp))
    print(f"live at {2 * LIVE_RATE:,} frames/s for {LIVE_SECONDS:g} s: {2 * live['sent_requests']:,} frames sent, "
          f"{live['frames_shown']:,} shown; longest wait from arrival to screen per tick: "
          f"p50 {live['lag_p50_ms']:.0f} ms, "
          f"p99 {live['lag_p99_ms']:.0f} ms, max {live['lag_max_ms']:.0f} ms; "
          f"largest backlog {live['backlog_max']:,} reads")
    with tempfile.TemporaryDirectory() as tmp:
        held = asyncio.run(_live(tmp, HELD))
    print(f"live at {2 * LIVE_RATE:,} frames/s, intercepting {HELD_FILTER} with {held['held']} frames held "
          f"throughout: {held['frames_shown']:,} shown; p99 wait from arrival to screen per tick "
          f"{held['lag_p99_ms']:.0f} ms (p50 {held['lag_p50_ms']:.0f} ms, max {held['lag_max_ms']:.0f} ms); "
          f"largest backlog {held['backlog_max']:,} reads")


if __name__ == "__main__":
    main()
