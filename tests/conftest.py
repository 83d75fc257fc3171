"""What every test process shares: a runtime folder of its own, and no
``whiztap`` process left running by a test that failed half-way.

``make test`` runs the tests in several processes at once (pytest-xdist).
``whiztap record --control`` puts its control socket in $XDG_RUNTIME_DIR/whiztap,
where ``whiztap ctl`` looks for it and where a new recorder clears the sockets
of killed ones: each test process gets its own folder there, so recorders
started by tests in other processes, or by the developer, are never found,
cleared or listed by a test's.  Short (a Unix socket path holds at most 107
bytes), under /tmp, and removed at the end.
"""

from __future__ import annotations

import os
import shutil
import tempfile

import pytest

from tests.browser_support import browser  # noqa: F401 - the fixture the HTML reports' tests take

_RUNTIME = "XDG_RUNTIME_DIR"
_runtime_key = pytest.StashKey[tuple[str, "str | None"]]()


def pytest_configure(config: pytest.Config) -> None:
    folder = tempfile.mkdtemp(prefix="wt-", dir="/tmp")
    os.chmod(folder, 0o700)
    config.stash[_runtime_key] = (folder, os.environ.get(_RUNTIME))
    os.environ[_RUNTIME] = folder


def pytest_unconfigure(config: pytest.Config) -> None:
    folder, before = config.stash.get(_runtime_key, (None, None))
    if folder is None:
        return
    if before is None:
        os.environ.pop(_RUNTIME, None)
    else:
        os.environ[_RUNTIME] = before
    shutil.rmtree(folder, ignore_errors=True)


def _quicker_pilot() -> None:
    """Textual's Pilot waits after every key and pause until the process looks
    idle: it sleeps 20 ms at a time and calls the app idle once a window used
    less than 5% of its time in CPU.  Windows of 5 ms (the same 5%) decide
    sooner, and the TUI tests ran 116 s -> 85 s serially; every test still
    waits for what it checks with ``tui_support.until``, so nothing depends
    on the window's length.  Textual's private module: if it moves, the
    tests only run at the default speed."""
    try:
        from textual import _wait
    except ImportError:
        return
    if hasattr(_wait, "SLEEP_GRANULARITY") and hasattr(_wait, "SLEEP_IDLE"):
        _wait.SLEEP_GRANULARITY = 0.005
        _wait.SLEEP_IDLE = 0.005 / 20


_quicker_pilot()


@pytest.fixture(autouse=True)
def _no_leftover_processes():
    """A test that fails before it stops what it started (a stub, a recorder)
    would leave it running for the rest of the suite: killed here."""
    from tests.cli_support import kill_leftovers

    yield
    kill_leftovers()
