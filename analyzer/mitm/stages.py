"""The proxy's stages, each call isolated, in the manner of mitmproxy's addons.

A stage is anything with some of the named hooks ``frame(frame)``,
``opened(conn)`` and ``closed(conn)``.  ``Stages`` calls them in order; when a
hook raises, what that call did to the frame is undone (the frame passes as
the stages before it left it), the failure is reported once per stage with its
traceback, and every other stage and the proxy go on.

A frame is offered only to the stages that may act on it: those switched on
(``active``, if a stage says) that may choose a frame of its direction and
kind (``chooses(direction, kind)``, if a stage says: a fault's ``dir:`` and
``kind:``).  The stages for each direction and kind are worked out once and
kept until a stage changes, so 255 faults on ``dir:c2s`` cost an answer from
the server nothing.  ``Stages`` also counts the frames of each direction, for
``QuietFaults`` to name a fault that chose none of them (``quiet.py``).
"""

from __future__ import annotations

import traceback
from collections.abc import Callable
from typing import Any

from whiztap.analyzer.mitm.frame import Frame
from whiztap.analyzer.mitm.quiet import QuietFaults, Quiet
from whiztap.analyzer.protocol.framing import ItemKind
from whiztap.analyzer.protocol.observations import Direction

Report = Callable[[str], None]


def stage_name(stage: Any) -> str:
    return getattr(stage, "name", None) or type(stage).__name__


class Stages:
    """The stages a frame goes through, in order (faults, scripts, interception)."""

    def __init__(self, report: Report, quiet: Quiet | None = None) -> None:
        """``quiet(stage, frames, ending)`` is told of a fault that chose none of
        ``frames`` of its direction (see ``quiet.py``)."""
        self.report = report
        self.items: list[Any] = []
        self.idle = True
        self.quiet = QuietFaults(quiet or (lambda stage, frames, ending: None))
        self._routes: dict[tuple[Direction, ItemKind], tuple[tuple[Any, Callable[[Frame], None]], ...]] = {}
        self._reported: set[int] = set()

    def set(self, items: list[Any]) -> None:
        self.items = items
        self.changed()

    def changed(self) -> None:
        """A stage was added, removed, switched on or off: ``idle`` is whether no
        stage can act on a frame now (each says so with ``active``; one that does
        not say, a script, always may), so frames need no decision; the routes
        are worked out again as frames need them.  Kept, not computed per read:
        the controller calls this whenever it changes a stage."""
        on = [stage for stage in self.items if getattr(stage, "active", True)]
        self.idle = not on
        self._routes.clear()
        self.quiet.watch(on)

    def _route(self, direction: Direction, kind: ItemKind) -> tuple[tuple[Any, Callable[[Frame], None]], ...]:
        """The stages, in order, that may act on a frame of ``direction`` and ``kind``, with their hook."""
        route = []
        for stage in self.items:
            hook = getattr(stage, "frame", None)
            chooses = getattr(stage, "chooses", None)
            if hook is not None and getattr(stage, "active", True) and (chooses is None or chooses(direction, kind)):
                route.append((stage, hook))
        self._routes[(direction, kind)] = tuple(route)
        return self._routes[(direction, kind)]

    def frame(self, frame: Frame) -> None:
        direction = frame.direction
        self.quiet.carried(direction)
        kind = frame.item.kind
        route = self._routes.get((direction, kind))
        if route is None:  # an empty route is kept too: that is the point
            route = self._route(direction, kind)
        for stage, hook in route:
            saved = frame.state()
            noted = len(frame.interventions)
            try:
                hook(frame)
            except Exception:  # a failing stage never touches the frame or the proxy
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
            except Exception:
                self._failed(stage, hook_name)

    def _failed(self, stage: Any, hook: str) -> None:
        if id(stage) in self._reported:
            return
        self._reported.add(id(stage))
        self.report(f"{stage_name(stage)}: its '{hook}' hook raised; the frame passes untouched and the proxy "
                    f"goes on (reported once)\n{traceback.format_exc().rstrip()}")
