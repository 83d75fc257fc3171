"""Scripts: hooks in a Python file, in the manner of mitmproxy's addons.

A script defines any of ``frame(flow)``, ``opened(conn)`` and ``closed(conn)``
at module level.  ``frame`` gets a ``Flow`` for each frame (in either
direction) on its way through the proxy and may let it pass (do nothing),
``drop()`` it, ``replace()`` it, ``delay()`` it or ``inject()`` another frame;
``opened``/``closed`` get the connection id.  A frame that may be a password
is shown to a script masked (``raw``, ``data``, ``text``, ``meaning``) unless
the run keeps secrets, so nothing a script logs can show it.  Each script is one stage
(``stages.py``): when a hook raises, its traceback is reported once for the
script on stderr, the frame passes as it came, and the proxy goes on.
"""

from __future__ import annotations

import importlib.util
import itertools
from pathlib import Path
from typing import Any

from whiztap.analyzer.analysis.item_filter import channel_of
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.describe import meaning
from whiztap.analyzer.protocol.frame_text import frame_from_text
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.mitm.frame import Frame, masked
from whiztap.analyzer.mitm.intercept import REDACTED_MEANING
from whiztap.analyzer.traffic import Cause, Source

HOOKS = ("frame", "opened", "closed")
_modules = itertools.count(1)


class ScriptError(WhiztapError):
    """A script cannot be loaded; one line naming the file and what to do."""


class Flow:
    """What a script's ``frame`` hook sees of a frame, and what it may do."""

    def __init__(self, frame: Frame, script: Script) -> None:
        self._frame = frame
        self._cause = Cause(Source.SCRIPT, script.name)

    conn = property(lambda self: self._frame.conn, doc="the connection id")
    direction = property(lambda self: self._frame.direction.value, doc='"c2s" or "s2c"')
    kind = property(lambda self: self._frame.kind.value, doc="command, response, config, set_config, ...")

    @property
    def raw(self) -> bytes:
        """The bytes as the sender sent them."""
        return self._shown(self._frame.raw)

    @property
    def data(self) -> bytes | None:
        """What will be delivered (None once dropped)."""
        data = self._frame.data
        return None if data is None else self._shown(data)

    @property
    def text(self) -> str:
        """The sent bytes as escaped text."""
        return escape(self.raw)

    @property
    def message(self) -> object:
        """The decoded message, or None."""
        return None if self._frame.hidden else self._frame.observation.message

    @property
    def meaning(self) -> str:
        """What it means, in words."""
        return REDACTED_MEANING if self._frame.hidden else meaning(self._frame.observation)

    def _shown(self, data: bytes) -> bytes:
        return masked(data) if self._frame.hidden else data

    @property
    def channel(self) -> int | None:
        """The channel it is about, also when the bytes alone do not say which
        message it is (``rr1-12--0--0-ss1`` is a Sensor Request or a switch off)."""
        return channel_of(self._frame.observation)

    def drop(self) -> None:
        self._frame.drop(self._cause)

    def replace(self, frame: bytes | str) -> None:
        """Deliver ``frame`` instead: bytes, escaped text or the console's words."""
        data = frame if isinstance(frame, bytes) else frame_from_text(frame)
        self._frame.replace(data, self._cause)

    def delay(self, seconds: float) -> None:
        self._frame.delay(int(seconds * 1e9), self._cause)

    def inject(self, frame: bytes | str, direction: str | None = None) -> None:
        """Send another frame on this connection (toward the server for
        "c2s", the client for "s2c"; default: this frame's way), after this one."""
        data = frame if isinstance(frame, bytes) else frame_from_text(frame)
        way = self._frame.direction if direction is None else Direction(direction)
        self._frame.inject(way, data, self._cause)


class Script:
    """One loaded script: a stage whose hooks call the script's functions."""

    def __init__(self, path: Path, module: Any) -> None:
        self.path = path
        self.name = path.name
        self.module = module

    def frame(self, frame: Frame) -> None:
        hook = getattr(self.module, "frame", None)
        if hook is not None:
            hook(Flow(frame, self))

    def opened(self, conn: int) -> None:
        hook = getattr(self.module, "opened", None)
        if hook is not None:
            hook(conn)

    def closed(self, conn: int) -> None:
        hook = getattr(self.module, "closed", None)
        if hook is not None:
            hook(conn)


def load_script(path: str | Path) -> Script:
    """Load a script file; ScriptError if it is missing, does not run, or has no hook."""
    path = Path(path)
    if not path.is_file():
        raise ScriptError(f"script {path}: no such file")
    spec = importlib.util.spec_from_file_location(f"whiztap_script_{next(_modules)}", path)
    if spec is None or spec.loader is None:
        raise ScriptError(f"script {path}: not a Python file")
    module = importlib.util.module_from_spec(spec)
    try:
        spec.loader.exec_module(module)
    except Exception as e:  # whatever a script does wrong at load time is the user's to fix
        raise ScriptError(f"script {path} failed to load: {type(e).__name__}: {e}") from None
    if not any(callable(getattr(module, hook, None)) for hook in HOOKS):
        raise ScriptError(f"script {path} defines none of the hooks {', '.join(HOOKS)}")
    return Script(path, module)
