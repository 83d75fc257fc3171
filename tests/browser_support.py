"""Headless Chromium for the tests of the HTML reports (tests/test_report_browser.py).

The browser is Debian's ``chromium`` (``.ci/install-test-deps`` installs it),
driven through Playwright's sync API with ``executable_path``: Playwright's
own browser download does not work on these machines.  One browser per test
process (a launch costs about half a second), a new context and page per
test.  Every request other than the report's own file is aborted and
recorded, so a report that reached for the network fails its test rather
than hanging on it.  Without Chromium or Playwright the tests skip, saying
how to install them.  The flags are those Chromium needs on a machine whose
network is closed (no background fetches, no component updates).
"""

from __future__ import annotations

import shutil
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest

CHROMIUM_ARGS = ["--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync"]
READY_MS = 20_000  # a generous bound on the page drawing itself; never a timing assertion


@dataclass
class Opened:
    """A report open in a page, and what the page did that it should not."""

    page: Any  # playwright.sync_api.Page
    console_errors: list[str] = field(default_factory=list)  # console messages of type error or warning
    page_errors: list[str] = field(default_factory=list)  # uncaught exceptions
    requests: list[str] = field(default_factory=list)  # every request but the document's own


def _chromium() -> str:
    found = shutil.which("chromium") or shutil.which("chromium-browser")
    if found is None:
        pytest.skip("no chromium: the HTML report's browser tests need Debian's chromium "
                    "(make test-deps installs it as root: apt-get install chromium)")
    return found


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """One headless Chromium for a test module.  Not for the whole session:
    Playwright's sync API keeps an event loop running in this thread while it
    is open, and every asyncio test after it would fail to start its own;
    pytest closes a module's fixtures before the next module's tests run."""
    executable = _chromium()
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        pytest.skip("no playwright: pip install -e '.[dev]' installs it")
    with sync_playwright() as playwright:
        launched = playwright.chromium.launch(executable_path=executable, headless=True, args=CHROMIUM_ARGS)
        try:
            yield launched
        finally:
            launched.close()


_contexts: list[Any] = []  # the last test's page, closed when the next opens one


def open_report(browser: Any, path: Path, *, width: int = 1400, height: int = 900) -> Opened:
    """``path`` in a new page, once its script has drawn it (``window.whiztapReady``)."""
    while _contexts:
        _contexts.pop().close()
    context = browser.new_context(viewport={"width": width, "height": height})
    _contexts.append(context)
    page = context.new_page()
    opened = Opened(page)
    document = path.resolve().as_uri()

    def route(r: Any) -> None:
        if r.request.url == document:
            r.continue_()
        else:
            opened.requests.append(r.request.url)
            r.abort()

    context.route("**/*", route)
    page.on("console", lambda m: opened.console_errors.append(f"{m.type}: {m.text}")
            if m.type in ("error", "warning") else None)
    page.on("pageerror", lambda e: opened.page_errors.append(str(e)))
    page.goto(document)
    page.wait_for_function("window.whiztapReady === true", timeout=READY_MS)
    return opened


def screenshot(opened: Opened, path: Path) -> None:
    """The window as it is now, as a PNG (docs/report.png)."""
    opened.page.screenshot(path=str(path))
