"""A line of whiztap's own on a recording's ``/log``: what the proxy has to say
about the recording rather than about a frame (today: a fault that chose no
frame, ``analyzer/mitm/quiet.py``).

``/log`` is Foxglove's Log panel; a violation's ``foxglove.Log`` says which
rule, connection and frame (``encode.encode_violation``).  A notice belongs to
no connection (``conn`` 0) and no frame: its ``name`` says who speaks (a
fault's name), ``file`` is ``whiztap``, ``line`` 0.  It travels from the proxy
to the writer process as its plain fields (``as_dict``/``Notice(**fields)``).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

from whiztap.analyzer.recording.encode import LOG_LEVELS, encode


@dataclass(frozen=True, slots=True)
class Notice:
    """One line for the recording's /log, at ``t_ns``; ``level`` as ``LOG_LEVELS`` names them."""

    t_ns: int
    name: str
    message: str
    level: str = "warning"
    conn: int = 0  # about no connection: the Recorder takes it in arrival order with the connections' events

    def as_dict(self) -> dict:
        return asdict(self)

    def log(self) -> bytes:
        """Its ``foxglove.Log`` message."""
        sec, nsec = divmod(self.t_ns, 1_000_000_000)
        return encode({"timestamp": {"sec": sec, "nsec": nsec}, "level": LOG_LEVELS[self.level],
                       "message": self.message, "name": self.name, "file": "whiztap", "line": 0})
