"""The proxy's stages, each call isolated, in the manner of mitmproxy's addons.

A stage is anything with some of the named hooks ``frame(frame)``,
``opened(conn)`` and ``closed(conn)``.  ``Stages`` calls them in order; when a
hook raises, what that call did to the frame is undone (the frame passes as
the stages before it left it), the failure is reported once per stage with its
traceback, and every other stage and the proxy go on.
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any

from whiztap.analyzer.mitm.frame import Frame

Report = Callable[[str], None]


def stage_name(stage: Any) -> str:
    return getattr(stage, "name", None) or type(stage).__name__


class Stages:
    """The stages a frame goes through, in order (faults, scripts, interception)."""

    def __init__(self, report: Report) -> None:
        self.report = report
        self.items: list[Any] = []
        self.idle = True
        self._reported: set[int] = set()

    def set(self, items: list[Any]) -> None:
        self.items = items
        self.changed()

    def changed(self) -> None:
        """A stage was switched on or off: ``idle`` is whether no stage can act
        on a frame now (each says so with ``active``; one that does not say, a
        script, always may), so frames need no decision.  Kept, not computed
        per read: the controller calls this whenever it changes a stage."""
        self.idle = not any(getattr(stage, "active", True) for stage in self.items)

    def frame(self, frame: Frame) -> None:
        for stage in self.items:
            hook = getattr(stage, "frame", None)
            if hook is None or not getattr(stage, "active", True):
                continue
            saved = frame.state()
            noted = len(frame.interventions)
            try:
                hook(frame)
            except Exception:  # noqa: BLE001 - a failing stage never touches the frame or the proxy
                frame.restore(saved)
                del frame.interventions[noted:]
                self._failed(stage, "frame")

    def call(self, hook_name: str, *args: Any) -> None:
        """``opened``/``closed`` and any other hook, isolated the same way."""
        for stage in self.items:
            hook = getattr(stage, hook_name, None)
            if hook is None:
                continue
            try:
                hook(*args)
            except Exception:  # noqa: BLE001
                self._failed(stage, hook_name)

    def _failed(self, stage: Any, hook: str) -> None:
        if id(stage) in self._reported:
            return
        self._reported.add(id(stage))
        self.report(f"{stage_name(stage)}: its '{hook}' hook raised; the frame passes untouched and the proxy "
                    f"goes on (reported once)\n{traceback.format_exc().rstrip()}")
