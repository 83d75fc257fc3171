"""The HTML report: its size and time to write, side by side with the JSON
report on the million-frame benchmark recording (bench_analyze's), and, for
a recording with 20,000 violations (10,000 listed, each with the frames
around it), how long headless Chromium takes until the page is interactive
and how long a sort and a filter of the violations take.

Write times are CPU seconds of this process (least of two); the HTML
report's extra is mostly its second read of the recording for the frames.
Browser times are wall-clock, median of three loads, from ``page.goto`` to
``window.whiztapReady`` (the page sets it once every table and plot is
drawn), measured in the page with ``performance.now()`` for the sort and the
filter.  Without Chromium or Playwright the browser rows say why they are
missing.
"""

from __future__ import annotations

import statistics
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

from benchmarks.bench_analyze import FRAMES, READ, _write, recording

BAD = b"rr1-0-- 5--0-ss1"  # a Normal Send with a space: PW-SYNTAX-SPACE, no answer owed
VIOLATIONS = 20_000


def _analyze_seconds(path: Path, out: Path, fmt: str) -> float:
    """``analyze`` in this process; it ends with sys.exit (its verdict), which is caught here."""
    from whiztap.analyzer.cli.analyze import analyze_command

    return _timed(lambda: _exits(analyze_command, [str(path), "--format", fmt, "-o", str(out), "-q", "--force"]))


def _exits(command: Any, args: list[str]) -> None:
    try:
        command.main(args, standalone_mode=False)
    except SystemExit:
        pass


def _timed(run: Callable[[], None]) -> float:
    """The least CPU time of two runs."""
    best = float("inf")
    for _ in range(2):
        began = time.process_time()
        run()
        best = min(best, time.process_time() - began)
    return best


def _browser_figures(page_path: Path) -> str:
    """Load, sort and filter times of the page in headless Chromium."""
    import shutil

    chromium = shutil.which("chromium")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        return "browser: skipped (no playwright: pip install -e '.[dev]')"
    if chromium is None:
        return "browser: skipped (no chromium: make test-deps installs it)"
    from tests.browser_support import CHROMIUM_ARGS

    loads, sorts, filters = [], [], []
    with sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, headless=True, args=CHROMIUM_ARGS)
        for _ in range(3):
            page = browser.new_page(viewport={"width": 1400, "height": 900})
            began = time.perf_counter()
            page.goto(page_path.as_uri())
            page.wait_for_function("window.whiztapReady === true", timeout=120_000)
            loads.append(time.perf_counter() - began)
            sorts.append(page.evaluate("""() => { const t = performance.now();
                document.querySelector('#t-violations th[data-key=t]').click(); return performance.now() - t; }"""))
            filters.append(page.evaluate("""() => { const s = document.querySelector(
                '#t-violations input[data-filter=text]'); const t = performance.now();
                s.value = '1.5'; s.dispatchEvent(new Event('input'));
                return performance.now() - t; }"""))
            page.close()
        browser.close()
    return (f"browser: interactive after {statistics.median(loads):.2f} s (median of 3: "
            f"{', '.join(f'{s:.2f}' for s in loads)}); sort {statistics.median(sorts):.0f} ms, "
            f"text filter {statistics.median(filters):.0f} ms")


def main() -> None:
    from whiztap.analyzer.analysis.report.page import page

    fixed = len(page("", {}).encode())
    path = recording("pipelined", FRAMES, READ)
    with tempfile.TemporaryDirectory() as folder:
        json_out, html_out = Path(folder) / "r.json", Path(folder) / "r.html"
        json_s = _analyze_seconds(path, json_out, "json")
        html_s = _analyze_seconds(path, html_out, "html")
        print(f"report of {FRAMES:,} items: json {json_s:.2f} s CPU ({json_out.stat().st_size / 1024:,.0f} KiB), "
              f"html {html_s:.2f} s CPU ({html_out.stat().st_size / 1024:,.0f} KiB; the page's own code "
              f"{fixed / 1024:.0f} KiB)")
        bad = Path(folder) / "violations.mcap"
        _write(bad, [(BAD * VIOLATIONS, b"")], READ)
        many = Path(folder) / "many.html"
        many_s = _analyze_seconds(bad, many, "html")
        print(f"report of {VIOLATIONS:,} violations (10,000 listed, with their frames): html "
              f"{many.stat().st_size / 2**20:.1f} MiB in {many_s:.2f} s CPU")
        print(_browser_figures(many))


if __name__ == "__main__":
    main()
