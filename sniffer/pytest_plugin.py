"""whiztap's pytest plugin: recorded sessions as regression tests.

Registered through the ``pytest11`` entry point, so every project that installs
whiztap has it.  docs/pytest-plugin.md has the full guide; in short:

- ``@pytest.mark.whiztap("session.mcap", target=..., password=..., **replay_options)``
  names a test's recording (relative to the test file; without a name,
  ``recordings/<module>/<test>.mcap`` beside it).
- ``whiztap_server``: an address to point the client under test at.  With
  ``--whiztap-record=none`` (the default) it is a stub serving the recording,
  and a request the recording has no answer for fails the test; with ``once``
  a missing recording is first made by recording through whiztap's proxy to
  the target; with ``all`` it is always re-recorded; with ``new_episodes`` the
  stub answers what the recording has and asks the target the rest, which is
  appended to the recording when the test ends (atomically: a test whose
  target failed leaves it as it was).
- ``whiztap_replay``: replays the recording's client side against the target
  and fails the test with the readable diff when an answer differs.
- ``whiztap_target``: the live server for recording and replaying ("HOST:PORT"
  from the marker or ``--whiztap-target``); override it in a conftest to start
  one, e.g. the simulator in a ``BackgroundLoop``.
- ``whiztap_proxy``: the recording proxy in the middle between the client under
  test and the target (docs/faults.md): faults for a ``with`` block, injected
  frames, and what the proxy changed, to assert on.

Servers run on an event loop in a background thread, so they serve synchronous
tests and asyncio tests alike.  Only pytest and the standard library are
imported until a fixture is used: the plugin loads in every pytest run of
every project that installs whiztap, most of which never use it, and the
proxy, the writer and the session model would cost them their import time
(and could break a run over a dependency it never needed).
"""

from __future__ import annotations

import asyncio
import os
import re
import threading
from collections.abc import Coroutine, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any, TypeVar

import pytest

if TYPE_CHECKING:
    from whiztap.sniffer.pytest_proxy import WhiztapProxy

MODES = ("none", "once", "new_episodes", "all")
T = TypeVar("T")
UPSTREAM_TIMEOUT_S = 5.0  # new_episodes: how long the target may take to connect, log in and answer


def pytest_addoption(parser: pytest.Parser) -> None:
    group = parser.getgroup("whiztap", "whiztap recordings as regression tests")
    group.addoption("--whiztap-record", choices=MODES, default="none",
                    help="none (default): serve recordings, fail on anything new; once: record the "
                         "missing ones through whiztap's proxy; new_episodes: serve what is recorded, ask the "
                         "target the rest and append it; all: re-record every one.")
    group.addoption("--whiztap-target", default=None, metavar="HOST:PORT",
                    help="The live server to record from and to replay against.")
    group.addoption("--whiztap-password", default=None, metavar="PASSWORD",
                    help="Winsock password for replays (default: the marker's, or $WHIZTAP_PASSWORD).")
    group.addoption("--whiztap-fail-unused", action="store_true", default=False,
                    help="Fail a test whose stub served a recording with requests the test never made.")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers", "whiztap(recording=None, *, target=None, password=None, **replay_options): the "
                   "recording (and live server) the whiztap_server and whiztap_replay fixtures use.")


@pytest.hookimpl(wrapper=True)
def pytest_runtest_call(item: pytest.Item) -> Iterator[None]:
    """Fail the test itself (not its teardown) when the stub met a request the
    recording has no answer for; that is the cause even when the client's
    error (a timeout waiting for the answer) came first."""
    try:
        return (yield)
    finally:
        server = getattr(item, "funcargs", {}).get("whiztap_server")
        if isinstance(server, WhiztapServer):
            server.check(unused=item.config.getoption("--whiztap-fail-unused"))


# -- running servers beside the test ---------------------------------------------------------


class BackgroundLoop:
    """An asyncio event loop in a daemon thread: servers started on it keep
    serving while a synchronous test (or another event loop) talks to them."""

    def __init__(self) -> None:
        self.loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self.loop.run_forever, name="whiztap-loop", daemon=True)
        self._thread.start()

    def run(self, coro: Coroutine[Any, Any, T], timeout: float | None = 60.0) -> T:
        """Run a coroutine on the loop and wait for its result."""
        return asyncio.run_coroutine_threadsafe(coro, self.loop).result(timeout)

    def close(self) -> None:
        self.loop.call_soon_threadsafe(self.loop.stop)
        self._thread.join()
        self.loop.close()

    def __enter__(self) -> BackgroundLoop:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# -- what a test names --------------------------------------------------------------------------


@dataclass(frozen=True)
class _Settings:
    recording: Path
    password: str | None
    options: dict[str, Any]  # the marker's replay options


def _marker(request: pytest.FixtureRequest) -> tuple[tuple, dict[str, Any]]:
    marker = request.node.get_closest_marker("whiztap")
    return (marker.args, dict(marker.kwargs)) if marker is not None else ((), {})


def _default_name(request: pytest.FixtureRequest) -> Path:
    test = re.sub(r"[^A-Za-z0-9_.-]+", "_", request.node.name).strip("_")
    return Path("recordings") / request.path.stem / f"{test}.mcap"


def _settings(request: pytest.FixtureRequest) -> _Settings:
    args, kwargs = _marker(request)
    name = kwargs.pop("recording", args[0] if args else None)
    path = Path(name) if name is not None else _default_name(request)
    if not path.is_absolute():
        path = request.path.parent / path
    kwargs.pop("target", None)
    password = (kwargs.pop("password", None) or request.config.getoption("--whiztap-password")
                or os.environ.get("WHIZTAP_PASSWORD"))
    return _Settings(path, password, kwargs)


def _address(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    if not port.isdigit():
        pytest.fail(f"whiztap: target must be HOST:PORT, got {text!r}", pytrace=False)
    return host.strip("[]") or "127.0.0.1", int(port)


@pytest.fixture
def whiztap_target(request: pytest.FixtureRequest) -> str | None:
    """The live server ("HOST:PORT"): the marker's ``target``, else
    ``--whiztap-target``.  Override this fixture to start one for the test."""
    return _marker(request)[1].get("target") or request.config.getoption("--whiztap-target")


@pytest.fixture
def whiztap_recording(request: pytest.FixtureRequest) -> Path:
    """The path of the test's recording (it may not exist yet)."""
    return _settings(request).recording


# -- the server fixture ------------------------------------------------------------------------------


class WhiztapServer:
    """Where the client under test connects: a stub serving the recording, or
    the recording proxy in front of the target (``recording`` is then True)."""

    def __init__(self, host: str, port: int, path: Path, recording: bool, stub: Any = None) -> None:
        self.host, self.port, self.path, self.recording = host, port, path, recording
        self._stub = stub
        self.mode = "none" if stub is None or stub.episodes is None else "new_episodes"

    @property
    def address(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def unanswered(self) -> list:
        """Requests the stub had no recorded answer for (``whiztap.sniffer.replay.stub.Unanswered``)."""
        return list(self._stub.unanswered) if self._stub is not None else []

    @property
    def unused(self) -> list:
        """Recorded requests no request of the test was answered from
        (``whiztap.sniffer.replay.near_miss.Recorded``), so far."""
        return self._stub.unused() if self._stub is not None else []

    @property
    def forwarded(self) -> int:
        """Requests asked of the target and recorded (``new_episodes``), so far."""
        return self._stub.forwarded if self._stub is not None else 0

    def check(self, unused: bool = False) -> None:
        """Fail the test on a request the recording has no answer for, and
        (``unused``: --whiztap-fail-unused) on a recorded one never made."""
        episodes = self._stub.episodes if self._stub is not None else None
        if episodes is not None and episodes.failure is not None:
            pytest.fail(f"whiztap: new_episodes: the target {episodes.upstream_text} failed: {episodes.failure}; "
                        f"nothing will be appended to {self.path}", pytrace=False)
        missing = self.unanswered
        if unused and not missing and (left := self.unused):
            from whiztap.analyzer.protocol.text import plural

            lines = "\n".join(f"  #{r.conn} request {r.position} {r.text}" for r in left)
            pytest.fail(f"whiztap: {plural(len(left), 'recorded request')} never asked for in {self.path} "
                        f"(--whiztap-fail-unused):\n{lines}\nre-record with --whiztap-record=all if the client "
                        f"changed on purpose", pytrace=False)
        if missing:
            from whiztap.analyzer.protocol.text import plural

            lines = "\n".join("\n".join(["  " + m.line(), *("    " + n for n in m.near_lines())])
                               for m in missing)
            pytest.fail(f"whiztap: {plural(len(missing), 'request')} not in {self.path} (record mode {self.mode}):\n"
                        f"{lines}\n"
                        f"re-record with --whiztap-record=all if the client changed on purpose", pytrace=False)


@pytest.fixture
def whiztap_server(request: pytest.FixtureRequest) -> Iterator[WhiztapServer]:
    """A stub serving the test's recording, or (record modes) a recording proxy
    in front of the target; see the module docstring."""
    mode = request.config.getoption("--whiztap-record")
    settings = _settings(request)
    path = settings.recording
    record = mode == "all" or (mode in ("once", "new_episodes") and not path.exists())
    if not record and not path.exists():
        pytest.fail(f"whiztap: no recording {path}; run pytest with --whiztap-record=once to make it",
                    pytrace=False)
    with BackgroundLoop() as background:
        needs_target = record or mode == "new_episodes"
        target = request.getfixturevalue("whiztap_target") if needs_target else None
        if needs_target and target is None:
            pytest.fail("whiztap: recording needs a live server: give the marker target=HOST:PORT, "
                        "--whiztap-target, or a whiztap_target fixture", pytrace=False)
        address = _address(target) if target is not None else None
        if record:
            assert address is not None
            yield from _recorded(background, path, address)
        else:
            yield from _stubbed(background, path, address)


def _load(path: Path) -> Any:
    """The recording's exchanges, or the test fails saying why."""
    from whiztap.analyzer.analysis.exchanges import load_exchanges
    from whiztap.analyzer.recording.scan import RecordingError

    try:
        return load_exchanges(str(path))
    except (OSError, RecordingError) as e:
        pytest.fail(f"whiztap: cannot read {path}: {e}", pytrace=False)


def _stubbed(background: BackgroundLoop, path: Path, target: tuple[str, int] | None) -> Iterator[WhiztapServer]:
    """A stub serving ``path``; with ``target`` (new_episodes) it asks the
    target what the recording lacks, appended when the test is over."""
    from whiztap.sniffer.replay.stub import Stub

    recording = _load(path)
    episodes = None if target is None else _episodes(path, target, recording.checksum_rule)

    async def start() -> Any:
        stub = Stub(recording, "127.0.0.1", 0, episodes=episodes)
        await stub.start()
        return stub

    stub = background.run(start())
    try:
        yield WhiztapServer("127.0.0.1", stub.port, path, False, stub)
    finally:
        background.run(stub.close())
        if episodes is not None:
            _append(episodes)


def _episodes(path: Path, target: tuple[str, int], checksum_rule: str) -> Any:
    """The new episodes of a new_episodes test, begun."""
    from whiztap.sniffer.record.writer import RecordingWriteError
    from whiztap.sniffer.replay.episodes import Episodes

    episodes = Episodes(path, target, checksum_rule, UPSTREAM_TIMEOUT_S)
    try:
        episodes.open()
    except (OSError, RecordingWriteError) as e:
        pytest.fail(f"whiztap: new_episodes: cannot record new episodes ({e})", pytrace=False)
    return episodes


def _append(episodes: Any) -> None:
    """Append a test's new episodes to its recording, or fail saying it is unchanged."""
    from whiztap.analyzer.recording.scan import RecordingError
    from whiztap.sniffer.record.writer import RecordingWriteError

    try:
        episodes.finish()
    except (OSError, RecordingError, RecordingWriteError) as e:
        pytest.fail(f"whiztap: new_episodes: cannot append to {episodes.path} ({e}); it is unchanged", pytrace=False)


def _recorded(background: BackgroundLoop, path: Path, target: tuple[str, int]) -> Iterator[WhiztapServer]:
    from whiztap.sniffer.record.record_run import Recording, RecordSettings

    path.parent.mkdir(parents=True, exist_ok=True)
    recording = Recording(RecordSettings(("127.0.0.1", 0), target, str(path), quiet=True))
    background.run(recording.start())
    try:
        yield WhiztapServer("127.0.0.1", recording.port, path, True)
    finally:
        background.run(recording.stop())
        if recording.error:
            pytest.fail(f"whiztap: recording {path} failed: {recording.error}", pytrace=False)


# -- the replay fixture ---------------------------------------------------------------------------------


class ReplayCheck:
    """Replays a recording against a live server; the test fails with the diff
    when an answer differs.  Call it from a synchronous test, or await
    ``run_async`` from an asyncio test (the target may then share its loop)."""

    def __init__(self, request: pytest.FixtureRequest) -> None:
        self._request = request

    def __call__(self, recording: str | Path | None = None, target: str | None = None, **options: Any) -> Any:
        with BackgroundLoop() as background:
            return background.run(self.run_async(recording, target or self._target(), **options), timeout=None)

    def _target(self) -> str:
        target = self._request.getfixturevalue("whiztap_target")
        if target is None:
            pytest.fail("whiztap: replay needs a live server: give target=, the marker's target, "
                        "--whiztap-target, or a whiztap_target fixture", pytrace=False)
        return target

    async def run_async(self, recording: str | Path | None = None, target: str | None = None,
                        **options: Any) -> Any:
        """Options: pace, rate, segments ("frames"/"exact"), compare, tolerance
        ({"sensor_value": 20}), ignore_fields, ignore_kinds, timeout, loop,
        conns, start, end, kinds, output; and password.  The result
        (``whiztap.sniffer.replay.events.ReplayResult``) when every answer matched."""
        from whiztap.sniffer.replay.engine import Replay
        from whiztap.sniffer.replay.options import ReplayError

        settings = _settings(self._request)
        path = Path(recording) if recording is not None else settings.recording
        if not path.is_absolute():
            path = self._request.path.parent / path
        target = target or self._target()
        if not path.exists():
            pytest.fail(f"whiztap: no recording {path}", pytrace=False)
        exchanges = _load(path)
        merged = {"checksum_rule": exchanges.checksum_rule, **settings.options, **options}
        password = merged.pop("password", None) or settings.password
        replay_options = _replay_options(merged, _address(target), password)
        try:
            result = await Replay(exchanges, replay_options).run()
        except ReplayError as e:
            how = {"password": "give password= (to whiztap_replay or the marker) or --whiztap-password"}
            pytest.fail(f"whiztap: {e.explained(how)}", pytrace=False)
        if result.error is not None:
            pytest.fail(f"whiztap: {result.error}", pytrace=False)
        if not result.ok:
            diffs = "\n".join(d.diff for d in result.differences)
            pytest.fail(f"whiztap: replay of {path} against {target} differs\n{diffs}\n{result.summary()}",
                        pytrace=False)
        return result


def _replay_options(options: dict[str, Any], target: tuple[str, int], password: str | None) -> Any:
    from whiztap.analyzer.analysis.compare import CompareError, CompareRules
    from whiztap.sniffer.replay.options import Pace, ReplayOptions
    from whiztap.sniffer.replay.plan import Selection

    tolerance = options.pop("tolerance", {})
    try:
        rules = CompareRules.parse(options.pop("compare", "structure"),
                                   [f"{k}={v}" for k, v in dict(tolerance).items()],
                                   options.pop("ignore_fields", ()), options.pop("ignore_kinds", ()))
    except CompareError as e:
        pytest.fail(f"whiztap: {e}", pytrace=False)
    selection = Selection(frozenset(options.pop("conns", ())), options.pop("start", None),
                          options.pop("end", None), frozenset(options.pop("kinds", ())))
    segments = options.pop("segments", "frames") == "exact"
    pace = Pace(options.pop("pace", "recorded"))
    try:
        return ReplayOptions(target=target, password=password.encode() if password else None, pace=pace,
                             segments=segments, rules=rules, selection=selection, **options)
    except TypeError as e:
        pytest.fail(f"whiztap: unknown replay option ({e})", pytrace=False)


@pytest.fixture
def whiztap_replay(request: pytest.FixtureRequest) -> ReplayCheck:
    """Replay the test's recording against ``whiztap_target`` and fail on a difference."""
    return ReplayCheck(request)



# -- the proxy in the middle ------------------------------------------------------------------------


@pytest.fixture
def whiztap_proxy(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[WhiztapProxy]:
    """The recording proxy in the middle between the client under test and
    ``whiztap_target``, recording into ``tmp_path``: faults, injected frames
    and what it changed, for the test to assert on (docs/pytest-plugin.md)."""
    target = request.getfixturevalue("whiztap_target")
    if target is None:
        pytest.fail("whiztap: whiztap_proxy needs a live server: give the marker target=HOST:PORT, "
                    "--whiztap-target, or a whiztap_target fixture", pytrace=False)
    from whiztap.sniffer.pytest_proxy import WhiztapProxy

    with BackgroundLoop() as background:
        proxy = WhiztapProxy(background.run, tmp_path / "whiztap-proxy.mcap", _address(target)).start()
        try:
            yield proxy
        finally:
            proxy.stop()
