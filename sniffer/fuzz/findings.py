"""A finding's files, the seeds read from recordings, and a finding run again.

Each finding becomes ``finding-N.mcap``, its minimal session played once more
through whiztap's own recording proxy (so it is an ordinary recording:
``analyze``, ``cat``, ``replay`` and the TUI read it, and the password is
masked as in any other), and ``test_finding_N.py``, a pytest that plays the
same session against the plugin's target (``--whiztap-target``, or a
``whiztap_target`` fixture) and fails while the server still fails it.  The
test holds the session as frames, the password by name only: it comes from
``--whiztap-password`` or ``$WHIZTAP_PASSWORD`` when the test runs.
"""

from __future__ import annotations

import asyncio
from pathlib import Path

from whiztap.analyzer.analysis.exchanges import load_exchanges
from whiztap.analyzer.fuzz.grammar import Frame, Knowledge, Session
from whiztap.analyzer.fuzz.judge import Verdict
from whiztap.analyzer.recording.scan import RecordingError
from whiztap.sniffer.fuzz.execute import FuzzError, checked, learn
from whiztap.sniffer.fuzz.run import Found
from whiztap.sniffer.record.record_run import Recording, RecordSettings

TEST_TEMPLATE = '''"""whiztap fuzz {id}: {kind}{rule}.

{detail}
Found by `whiztap fuzz server` (seed {seed}, execution {execution}); the session
below is {shrunk}.  Run it against the server under test:

    pytest {test_name} --whiztap-target HOST:PORT --whiztap-password PASSWORD

(or WHIZTAP_PASSWORD in the environment; a VPN server needs none).  It fails
while the server still fails this way; {recording} holds the same session
as a whiztap recording (`whiztap replay`, `whiztap analyze`).
"""

import os

import pytest

from whiztap.analyzer.fuzz.grammar import Frame
from whiztap.sniffer.fuzz.findings import reproduce

SESSION = (
{frames})


@pytest.mark.whiztap("{recording}")
def test_{name}(whiztap_target, request):
    if whiztap_target is None:
        pytest.fail("give the server under test: --whiztap-target HOST:PORT", pytrace=False)
    password = request.config.getoption("--whiztap-password") or os.environ.get("WHIZTAP_PASSWORD", "")
    verdict = reproduce(whiztap_target, password, SESSION)
    assert verdict is None, f"{{verdict.kind}}: {{verdict.detail}}"
'''


def frame_source(frame: Frame) -> str:
    """A frame as Python source (the password by name only)."""
    args = [repr(frame.data)] if frame.data else []
    if frame.cuts:
        args.append(f"cuts={frame.cuts!r}")
    if frame.pipelined:
        args.append("pipelined=True")
    if frame.secret:
        args.append(f"secret={frame.secret!r}")
    return f"Frame({', '.join(args)})"


def test_source(found: Found, seed: int) -> str:
    v = found.verdict
    return TEST_TEMPLATE.format(
        id=found.id, kind=v.kind, rule=f" ({v.rule})" if v.rule else "", detail=v.detail, seed=seed,
        execution=found.execution, shrunk="shrunk to a minimum" if found.shrunk else "as found (not shrunk)",
        test_name=f"test_finding_{found.number}.py", recording=f"{found.id}.mcap", name=f"finding_{found.number}",
        frames="".join(f"    {frame_source(f)},\n" for f in found.session))


async def record(path: Path, address: tuple[str, int], session: Session, knowledge: Knowledge, password: bytes,
                 deadline: float) -> None:
    """Play ``session`` through the recording proxy in front of ``address`` into ``path``."""
    recording = Recording(RecordSettings(("127.0.0.1", 0), address, str(path), quiet=True))
    await recording.start()
    try:
        await checked(("127.0.0.1", recording.port), session, knowledge, password, deadline)
    finally:
        await recording.stop()
    if recording.error:
        raise FuzzError(f"{path}: the recording failed ({recording.error})")


async def write(found: Found, directory: Path, address: tuple[str, int], knowledge: Knowledge, password: bytes,
                deadline: float, seed: int) -> None:
    """``finding-N.mcap`` and ``test_finding_N.py`` in ``directory``."""
    path = directory / f"{found.id}.mcap"
    await record(path, address, found.session, knowledge, password, deadline)
    test = directory / f"test_finding_{found.number}.py"
    test.write_text(test_source(found, seed))
    found.recording, found.test = str(path), str(test)


def reproduce(target: str, password: str, session: Session, deadline: float = 1.0) -> Verdict | None:
    """Play a finding's session against ``target`` ("HOST:PORT") once: its
    verdict, None when the server now gets through it."""
    host, _, port = target.rpartition(":")
    address = (host.strip("[]") or "127.0.0.1", int(port))

    async def once() -> Verdict | None:
        knowledge = await learn(address, password.encode(), deadline)
        outcome, _ = await checked(address, session, knowledge, password.encode(), deadline)
        return outcome.verdict

    return asyncio.run(once())


def recorded_seeds(paths: tuple[str, ...]) -> tuple[tuple[tuple[str, bytes], ...], ...]:
    """Each recorded connection's client items, (kind, bytes), from ``--from`` recordings."""
    seeds = []
    for path in paths:
        try:
            sessions = load_exchanges(path)
        except OSError as e:
            raise FuzzError(f"{path}: cannot read ({e.strerror or e})") from None
        except RecordingError as e:
            raise FuzzError(str(e) if path in str(e) else f"{path}: not a readable recording ({e})") from None
        for conn in sessions.connections:
            seeds.append(tuple((item.obs.item.kind.value, item.obs.item.raw) for item in conn.items))
    return tuple(s for s in seeds if s)
