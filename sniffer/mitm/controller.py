"""The control layer of the proxy in the middle: one object that the JSON
control API, ``whiztap ctl``, the pytest fixture and the TUI all drive, so
they can never disagree.

It owns the stages every frame goes through, in this order: the faults (in
the order they were added), the scripts, then interception (so a person sees
the frame as it is about to be sent).  Frames typed by a person (an edit, an
injection) are checked before they are sent: one that breaks a rule is
refused unless ``force`` is given, so the spec is broken only on purpose.
"""

from __future__ import annotations

import asyncio
import json
import itertools
import random
from collections.abc import Callable, Iterable
from pathlib import Path
from typing import Any

from whiztap.analyzer.mitm.spec import FaultSpec, parse_fault
from whiztap.analyzer.protocol.frame_text import check_frame, frame_from_text
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits
from whiztap.sniffer.mitm.faults import Fault
from whiztap.sniffer.mitm.intercept import HeldFrames, Intercept
from whiztap.sniffer.mitm.middle import Middle
from whiztap.sniffer.mitm.stages import Stages, stage_name

EXPIRE_S = 0.5


def middle_metadata(faults: Iterable[FaultSpec], seed: int | None) -> dict[str, str]:
    """The metadata of a recording made with the proxy in the middle (docs/faults.md):
    what a replay needs to re-apply its faults (``--faults-from-recording``)."""
    listed = [{"name": f.name, "spec": f.text} for f in faults]
    return {"middle": "yes", "faults": json.dumps(listed), "seed": "" if seed is None else str(seed)}


class ControlError(ValueError):
    """A control request cannot be carried out; the message says why, in one line."""


class Controller:
    def __init__(self, *, seed: int | None = None, hold_timeout: float = 60.0, checksum_rule: str = "dev-sum",
                 limits: Limits = Limits(), report: Callable[[str], None] = print) -> None:
        self.rng = random.Random(seed)
        self.seed = seed
        self.checksum_rule = checksum_rule
        self.limits = limits
        self.report = report
        self.stages = Stages(report)
        self.faults: list[Fault] = []
        self.scripts: list[Any] = []
        self.intercept = Intercept()
        self.clock: Callable[[], int] = lambda: 0  # the proxy's, from attach()
        self.emit: Callable[[object], None] = lambda event: None
        self.held = HeldFrames(hold_timeout, lambda: self.clock(), lambda event: self.emit(event))
        self.middles: dict[int, Middle] = {}
        self._fault_ids = itertools.count(1)
        self._expiry: asyncio.Task | None = None
        self._restage()

    def attach(self, clock: Callable[[], int], emit: Callable[[object], None]) -> None:
        """The proxy's clock and its consumers (interventions and deliveries are traffic events)."""
        self.clock, self.emit = clock, emit

    def _restage(self) -> None:
        self.stages.items = [*self.faults, *self.scripts, self.intercept]

    # -- connections -------------------------------------------------------------------------------

    def open(self, connection: Any) -> Middle:
        middle = self.middles[connection.id] = Middle(self, connection)
        for fault in self.faults:
            middle.schedule(fault)
        self.stages.call("opened", connection.id)
        if self._expiry is None:
            self._expiry = asyncio.get_running_loop().create_task(self._expire())
        return middle

    def closed(self, conn_id: int) -> None:
        middle = self.middles.pop(conn_id, None)
        if middle is not None:
            middle.close()
        for fault in self.faults:
            fault.forget(conn_id)
        self.held.forget_conn(conn_id)
        self.stages.call("closed", conn_id)

    async def _expire(self) -> None:
        while True:
            await asyncio.sleep(EXPIRE_S)
            try:
                self.held.expire()
            except Exception as e:  # noqa: BLE001 - the expiry loop outlives any one frame
                self.report(f"hold timeout: {type(e).__name__}: {e}")

    def stop(self) -> None:
        if self._expiry is not None:
            self._expiry.cancel()
            self._expiry = None

    def connections(self) -> list[dict]:
        return [{"conn": m.conn_id, "client": m.connection.client_addr,
                 "c2s_queued": m.lanes[Direction.C2S].queued, "s2c_queued": m.lanes[Direction.S2C].queued}
                for m in self.middles.values()]

    # -- faults ----------------------------------------------------------------------------------

    def add_fault(self, spec: str | FaultSpec, name: str = "") -> Fault:
        """Add a fault (FaultSpecError if the text does not parse; ControlError if the name is taken)."""
        if isinstance(spec, str):
            spec = parse_fault(spec, name)
        if spec.name.isdigit():
            raise ControlError(f"a fault's name cannot be a number ({spec.name!r}): numbers are fault ids")
        if spec.name and any(f.name == spec.name for f in self.faults):
            raise ControlError(f"a fault named {spec.name!r} is already in force")
        fault = Fault(spec, self.rng, self.clock(), id=next(self._fault_ids))
        self.faults.append(fault)
        self._restage()
        for middle in self.middles.values():
            middle.schedule(fault)
        return fault

    def fault(self, key: str | int) -> Fault:
        for fault in self.faults:
            if str(fault.id) == str(key) or fault.name == key:
                return fault
        raise ControlError(f"no fault {key!r} (see the fault list)")

    def remove_fault(self, key: str | int) -> Fault:
        fault = self.fault(key)
        self.faults.remove(fault)
        self._restage()
        return fault

    def enable_fault(self, key: str | int, enabled: bool) -> Fault:
        fault = self.fault(key)
        fault.enabled = enabled
        return fault

    # -- scripts ---------------------------------------------------------------------------------

    def add_script(self, script: Any) -> None:
        self.scripts.append(script)
        self._restage()

    # -- interception and injection ----------------------------------------------------------------

    def set_intercept(self, text: str | None) -> None:
        try:
            self.intercept.set(text)
        except ValueError as e:
            raise ControlError(f"intercept filter: {e}") from None

    def held_frames(self) -> list[dict]:
        now = self.clock()
        return [h.as_dict(now) for h in self.held.frames.values()]

    def release(self, held_id: int, edit: str | None = None, force: bool = False) -> dict:
        held = self.held.frames.get(held_id)
        if held is None:
            raise ControlError(f"no held frame #{held_id} (it was released, dropped or timed out)")
        data = None if edit is None else self.checked(edit, held.direction, force)
        self.held.release(held_id, data, cause="hand edit" if data is not None else "hand")
        return held.as_dict(self.clock())

    def drop(self, held_id: int) -> dict:
        held = self.held.frames.get(held_id)
        if held is None:
            raise ControlError(f"no held frame #{held_id} (it was released, dropped or timed out)")
        dropped = held.as_dict(self.clock())  # before the release empties it: the answer names what was dropped
        self.held.release(held_id, drop=True, cause="hand drop")
        return dropped

    def release_all(self) -> int:
        ids = list(self.held.frames)
        for held_id in ids:
            self.held.release(held_id)
        return len(ids)

    def inject(self, conn: int, direction: Direction | str, text: str, force: bool = False) -> bytes:
        """Send a typed frame on connection ``conn`` toward the server (c2s) or the client (s2c)."""
        try:
            direction = Direction(direction)
        except ValueError:
            raise ControlError(f"direction must be c2s or s2c, got {direction!r}") from None
        middle = self.middles.get(int(conn))
        if middle is None:
            raise ControlError(f"no open connection #{conn}")
        data = self.checked(text, direction, force)
        middle.inject(direction, data, "injection")
        return data

    def checked(self, text: str, direction: Direction, force: bool) -> bytes:
        """The frame ``text`` stands for, if it breaks no rule (or ``force``)."""
        try:
            data = frame_from_text(text)
        except ValueError as e:
            raise ControlError(str(e)) from None
        if not force:
            broken = check_frame(data, direction, self.checksum_rule)
            if broken:
                rules = "; ".join(f"{v.rule_id}: {v.detail}" for v in broken)
                raise ControlError(f"the frame breaks a rule ({rules}); send it anyway with force")
        return data

    def metadata(self) -> dict[str, str]:
        """The metadata of a recording made through this controller (``middle_metadata``)."""
        return middle_metadata([f.spec for f in self.faults], self.seed)

    def state(self) -> dict:
        return {"faults": [f.as_dict() for f in self.faults], "intercept": self.intercept.text,
                "held": self.held_frames(), "connections": self.connections(), "seed": self.seed,
                "scripts": [stage_name(s) for s in self.scripts]}


def load_fault_file(controller: Controller, path: str | Path) -> None:
    from whiztap.analyzer.mitm.spec import load_faults

    for spec in load_faults(path):
        controller.add_fault(spec)
