"""What a replay is asked to do (``ReplayOptions``), and the error it stops with.

Shared by the replay engine, the stub (which takes its ``Pace``) and the front
ends that build the options: the command line, the TUI and the pytest plugin.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum
from typing import TYPE_CHECKING

from whiztap.analyzer.analysis.compare import CompareRules
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.protocol.checksum import DEFAULT_CHECKSUM_RULE
from whiztap.sniffer.replay.plan import Selection

if TYPE_CHECKING:
    from whiztap.analyzer.mitm.spec import FaultSpec
    from whiztap.analyzer.protocol.messages import ChannelConfig


class Pace(StrEnum):
    RECORDED = "recorded"
    LOCKSTEP = "lockstep"
    MAX = "max"


class ReplayError(WhiztapError):
    """The replay cannot start or go on (one line for the user).

    ``missing`` names a setting the replay needs and was not given ("target",
    "password"): each front end says how to give it in its own terms
    (``explained``); the command line and the TUI check the target themselves
    before a replay exists, so only the password reaches them this way.
    """

    def __init__(self, message: str, missing: str | None = None) -> None:
        super().__init__(message)
        self.missing = missing

    def explained(self, how: dict[str, str]) -> str:
        """The message, with ``how[missing]`` saying how to give what is missing."""
        hint = how.get(self.missing or "")
        return f"{self}: {hint}" if hint else str(self)


@dataclass(frozen=True, slots=True)
class ReplayOptions:
    target: tuple[str, int] | None = None
    password: bytes | None = None  # None: the recorded one if it was kept
    pace: Pace = Pace.RECORDED
    rate: float = 1.0
    segments: bool = False  # re-send the recorded TCP reads instead of whole frames
    rules: CompareRules = CompareRules()
    timeout: float = 2.0  # for each expected answer and the handshake
    connect_timeout: float = 5.0
    loop: int = 1
    selection: Selection = Selection()
    output: str | None = None  # write the replayed session here as a recording
    checksum_rule: str = DEFAULT_CHECKSUM_RULE
    # faults to apply between the replay and the target, through a proxy in the
    # middle (sniffer/replay/faults.py); none: the replay connects to the target itself
    faults: tuple[FaultSpec, ...] = ()
    fault_seed: int | None = None  # for the faults' prob:, jitter: and slice ranges
    # judge the answers against what the recorded *client* received (a recording made in the middle:
    # its /tcp/delivered), not what the recorded server sent: a replay under the recording's own
    # faults (--faults-from-recording) then passes when it reproduces what the recorded client went through
    reproduce: bool = False
    # --channels/--assume-config: the map the replayed sessions start from, for a client that never fetched it
    assumed_channels: tuple[ChannelConfig, ...] = ()

    @property
    def address(self) -> tuple[str, int]:
        """``target``, which every replay but a dry run needs (``Replay.check`` says so first)."""
        if self.target is None:
            raise ReplayError("no target", missing="target")
        return self.target
