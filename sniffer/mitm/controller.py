"""The control layer of the proxy in the middle: one object that the JSON
control API, ``whiztap ctl``, the pytest fixture and the TUI all drive, so
they can never disagree.

It owns what every connection's sans-IO core shares (``MiddleContext``: the
stages every frame goes through, in this order: the faults in the order they
were added, the scripts, then interception, so a person sees the frame as it
is about to be sent; the held frames; chance) and each connection's core with
the shell that carries out its commands.  Frames typed by a person (an edit,
an injection) are checked before they are sent: one that breaks a rule is
refused unless ``force`` is given, so the spec is broken only on purpose.
"""

from __future__ import annotations

import json
import random
from collections.abc import Callable, Iterable, Sequence
from functools import partial
from pathlib import Path
from typing import Any, Protocol

from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.mitm.commands import Closing, Command, Full
from whiztap.analyzer.mitm.core import MiddleContext, MiddleCore
from whiztap.analyzer.mitm.faults import MAX_DUP_FAULTS, MAX_FAULTS, Fault
from whiztap.analyzer.mitm.intercept import Held, HeldFrames, Intercept
from whiztap.analyzer.mitm.spec import FaultSpec, parse_fault
from whiztap.analyzer.mitm.stages import Stages, stage_name
from whiztap.analyzer.protocol.frame_text import check_frame, frame_from_text
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.session import Limits
from whiztap.analyzer.protocol.text import escape, plural, printable
from whiztap.analyzer.traffic import Cause, Source, TrafficEvent

def middle_metadata(faults: Iterable[FaultSpec], seed: int | None) -> dict[str, str]:
    """The metadata of a recording made with the proxy in the middle (docs/faults.md):
    what a replay needs to re-apply its faults (``--faults-from-recording``)."""
    listed = [{"name": f.name, "spec": f.text} for f in faults]
    return {"middle": "yes", "faults": json.dumps(listed), "seed": "" if seed is None else str(seed)}


class ControlError(WhiztapError, ValueError):
    """A control request cannot be carried out; the message says why, in one
    line.  ``status`` is the HTTP status the control API answers with: 400 a
    refused request, 404 nothing by that id, 409 the connection is closing,
    429 too much already waits to be delivered."""

    def __init__(self, message: str, status: int = 400) -> None:
        super().__init__(message)
        self.status = status


class Shell(Protocol):
    """What carries out a connection's commands (``shell.MiddleShell`` on the proxy's loop)."""

    @property
    def client_addr(self) -> str: ...

    def run(self, commands: list[Command]) -> None: ...


class Controller:
    def __init__(self, *, seed: int | None = None, hold_timeout: float = 60.0, checksum_rule: str = "dev-sum",
                 limits: Limits = Limits(), redact: bool = True, report: Callable[[str], None] = print) -> None:
        self.seed = seed
        self.checksum_rule = checksum_rule
        self.report = report
        self.scripts: list[Any] = []
        self.intercept = Intercept()
        self.context = MiddleContext(Stages(report, self._quiet), rng=random.Random(seed), limits=limits,
                                     checksum_rule=checksum_rule, redact=redact,
                                     hold_timeout_ns=int(hold_timeout * 1e9))
        self.clock: Callable[[], int] = lambda: 0  # the proxy's, from attach()
        self.emit: Callable[[TrafficEvent], None] = lambda event: None
        # analyze's verdict on the traffic so far, as the recording's writer judges it (None: not known)
        self.verdict: Callable[[], dict | None] = lambda: None
        # a line about a fault for the recording's /log: (the fault's name, the line, when); the Recording's
        self.log: Callable[[str, str, int], None] = lambda name, line, t_ns: None
        self.quiet_at_end: list[Fault] = []  # the faults that chose no frame, once the proxy stopped (``end``)
        self.cores: dict[int, tuple[MiddleCore, Shell]] = {}
        self._fault_ids = 0
        self._restage()

    @property
    def faults(self) -> list[Fault]:
        return self.context.faults

    @property
    def held(self) -> HeldFrames:
        return self.context.held

    def attach(self, clock: Callable[[], int], emit: Callable[[TrafficEvent], None]) -> None:
        """The proxy's clock and its consumers (interventions and deliveries are traffic events)."""
        self.clock, self.emit = clock, emit

    def _restage(self) -> None:
        self.context.stages.set([*self.faults, *self.scripts, self.intercept])

    # -- connections -------------------------------------------------------------------------------

    def open(self, conn: int, shell: Shell) -> tuple[MiddleCore, list[Command]]:
        """A connection opened: its core, and what it asks for first (a timer
        for the timed faults in force), for ``shell`` to carry out."""
        now = self.clock()
        core = MiddleCore(conn, now, self.context)
        self.cores[conn] = (core, shell)
        commands: list[Command] = []
        for fault in self.faults:
            commands += core.schedule(fault, now)
        self.context.stages.call("opened", conn)
        return core, commands

    def closed(self, conn: int) -> None:
        entry = self.cores.pop(conn, None)
        if entry is not None:
            core, shell = entry
            shell.run(core.closed(self.clock()))
        for fault in self.faults:
            fault.forget(conn)
        self.context.stages.call("closed", conn)

    def connections(self) -> list[dict]:
        return [{"conn": conn, "client": shell.client_addr, "c2s_queued": core.lanes[Direction.C2S].queued,
                 "s2c_queued": core.lanes[Direction.S2C].queued, "closing": core.closing}
                for conn, (core, shell) in self.cores.items()]

    def _run(self, conn: int, act: Callable[[MiddleCore, int], list[Command]]) -> None:
        """A control command on connection ``conn``'s core, its commands carried out."""
        entry = self.cores.get(conn)
        if entry is None:
            raise ControlError(f"no open connection #{conn}", 404)
        core, shell = entry
        try:
            commands = act(core, self.clock())
        except Closing as e:
            raise ControlError(str(e), 409) from None
        except Full as e:
            raise ControlError(str(e), 429) from None
        shell.run(commands)

    # -- faults ----------------------------------------------------------------------------------

    def add_fault(self, spec: str | FaultSpec, name: str = "") -> Fault:
        """Add a fault (FaultSpecError if the text does not parse; ControlError if the name is taken)."""
        if isinstance(spec, str):
            spec = parse_fault(spec, name)
        if spec.name.isdigit():
            raise ControlError(f"a fault's name cannot be a number ({spec.name!r}): numbers are fault ids")
        if spec.name and any(f.name == spec.name for f in self.faults):
            raise ControlError(f"a fault named {spec.name!r} is already in force")
        if len(self.faults) >= MAX_FAULTS:
            raise ControlError(f"{MAX_FAULTS} faults are in force, the most there may be at once; remove one first")
        if spec.action == "dup" and sum(f.spec.action == "dup" for f in self.faults) >= MAX_DUP_FAULTS:
            raise ControlError(f"{MAX_DUP_FAULTS} dup faults are in force, the most there may be "
                               f"(a frame goes out at most {MAX_DUP_FAULTS + 1} times)")
        self._fault_ids += 1
        fault = Fault(spec, self.context.rng, self.clock(), id=self._fault_ids)
        self.faults.append(fault)
        self._restage()
        now = self.clock()
        for core, shell in self.cores.values():
            shell.run(core.schedule(fault, now))
        return fault

    def _quiet(self, fault: Fault, frames: int, ending: bool) -> None:
        """A fault chose none of ``frames`` of its direction (``quiet.py``): said
        where warnings go (stderr, the TUI's notices) and on the recording's /log."""
        way = "" if fault.direction is None else f"{fault.direction.value} "
        line = f"{fault.name} ({fault.spec.text}) chose none of the {plural(frames, way + 'frame')} " + \
            ("it saw" if ending else "since it was put in force; is its SPEC what you meant?")
        self.report(f"warning: fault {line}")
        self.log(fault.name, f"fault {line}", self.clock())
        if ending:
            self.quiet_at_end.append(fault)

    def end(self) -> list[Fault]:
        """The proxy has stopped: each fault in force that saw frames and chose
        none of them is named (as ``_quiet`` says); those faults."""
        self.quiet_at_end = []
        self.context.stages.quiet.end()
        return self.quiet_at_end

    def fault(self, key: str | int) -> Fault:
        for fault in self.faults:
            if str(fault.id) == str(key) or fault.name == key:
                return fault
        raise ControlError(f"no fault {key!r} (see the fault list)", 404)

    def remove_fault(self, key: str | int) -> Fault:
        fault = self.fault(key)
        self.faults.remove(fault)
        self._restage()
        return fault

    def enable_fault(self, key: str | int, enabled: bool) -> Fault:
        fault = self.fault(key)
        fault.enabled = enabled
        self.context.stages.changed()
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
        self.context.stages.changed()

    def held_frames(self) -> list[dict]:
        now = self.clock()
        return [h.as_dict(now) for h in self.held.frames.values()]

    def _held(self, held_id: int) -> Held:
        held = self.held.get(held_id)
        if held is None:
            raise ControlError(f"no held frame #{held_id} (it was released, dropped or timed out, or its "
                               f"connection ended)", 404)
        return held

    def release(self, held_id: int, edit: str | None = None, force: bool = False) -> dict:
        held = self._held(held_id)
        if edit is not None and held.hidden and edit == escape(held.shown):
            edit = None  # a password's mask sent back unchanged (the editor shows it masked): it goes as it came
        data = None if edit is None else self.checked(edit, held.direction, force)
        cause = Cause(Source.HAND, "edit" if data is not None else "")
        self._run(held.conn, lambda core, now: core.release(held, data, False, cause, now))
        if data is not None:
            held.data = data
        return held.as_dict(self.clock())

    def drop(self, held_id: int) -> dict:
        held = self._held(held_id)
        dropped = held.as_dict(self.clock())  # the answer names what was dropped
        self._run(held.conn, lambda core, now: core.release(held, None, True, Cause(Source.HAND, "drop"), now))
        return dropped

    def release_all(self) -> int:
        released = 0
        for held in list(self.held.frames.values()):
            try:
                self._run(held.conn, partial(_release_as_it_is, held))
            except ControlError:
                continue  # its connection is closing: it goes (or expires) with it
            released += 1
        return released

    def inject(self, conn: int, direction: Direction | str, text: str, force: bool = False) -> bytes:
        """Send a typed frame on connection ``conn`` toward the server (c2s) or the client (s2c)."""
        try:
            direction = Direction(direction)
        except ValueError:
            raise ControlError(f"direction must be c2s or s2c, got {direction!r}") from None
        if int(conn) not in self.cores:
            raise ControlError(f"no open connection #{conn}", 404)
        data = self.checked(text, direction, force)
        way = direction
        self._run(int(conn), lambda core, now: core.inject(way, data, Cause(Source.INJECTION), now))
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
                "scripts": [stage_name(s) for s in self.scripts], "verdict": self.verdict()}


def _release_as_it_is(held: Held, core: MiddleCore, now: int) -> list[Command]:
    """A held frame let go unchanged, by hand (``release_all``)."""
    return core.release(held, None, False, Cause(Source.HAND), now)


def add_start_faults(controller: Controller, files: Iterable[str | Path], specs: Sequence[FaultSpec]) -> None:
    """The faults a run starts with (``--faults FILE``, then ``--fault SPEC``),
    added in that order.  FaultSpecError for a file that does not read;
    ControlError for a fault refused (a name taken, one fault too many),
    naming its file."""
    from whiztap.analyzer.mitm.fault_file import load_faults

    for path in files:
        try:
            for spec in load_faults(path):
                controller.add_fault(spec)
        except ControlError as e:
            raise ControlError(f"{printable(str(path))}: {e}") from None
    given = len(controller.faults) + len(specs)
    if given > MAX_FAULTS:
        raise ControlError(f"{given} faults given (--faults and --fault); at most {MAX_FAULTS} may be in force at once")
    for spec in specs:
        controller.add_fault(spec)
