"""Bisect (``b``): to the first frame breaking a rule, and to where two
connections part; and the replay screen's faults: none, the recording's, or typed."""

from __future__ import annotations

import asyncio
import contextlib
from pathlib import Path

import pytest

from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.rules import Severity
from whiztap.analyzer.mitm.spec import parse_fault
from whiztap.sniffer.record.record_run import MiddleSettings
from tests.record_support import LOCAL, StepServer, closed_port, play_client, recording
from tests.test_replay_faults import DROP, ROUNDS, record, simulator
from tests.tui_support import SAMPLES, SIZE, loaded, until
from whiztap.tui.app import WhiztapApp
from whiztap.tui.screens.bisect import (
    BisectError,
    BisectPrompt,
    ConnectionPair,
    DivergenceScreen,
    RuleQuery,
    parse_query,
)
from whiztap.tui.screens.replay_screen import ReplayScreen, split_specs
from whiztap.tui.data.sources import FileSource


@contextlib.asynccontextmanager
async def loaded_app(path: Path | str):
    """The app on a recording, loaded: (app, pilot)."""
    app = WhiztapApp(FileSource(str(path)))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        yield app, pilot


async def ask(pilot, query: str) -> BisectPrompt:
    """``b``, the prompt emptied, ``query`` typed and submitted."""
    await pilot.press("b")
    prompt = pilot.app.screen
    assert isinstance(prompt, BisectPrompt)
    prompt.query_one("#bisect-query").value = query
    await pilot.press("enter")
    return prompt


def said(prompt: BisectPrompt) -> str:
    return str(prompt.query_one("#bisect-said").render())


# -- the query --------------------------------------------------------------------------------------


@pytest.mark.parametrize(("text", "wanted"), [
    ("PW-PAIR-UNANSWERED", RuleQuery("PW-PAIR-UNANSWERED", frozenset({"PW-PAIR-UNANSWERED"}))),
    (" pw-pair ", RuleQuery("PW-PAIR", frozenset({"PW-PAIR-UNANSWERED", "PW-PAIR-UNSOLICITED"}))),
    ("Error", RuleQuery("error", severity=Severity.ERROR)),
    ("1 2", ConnectionPair(1, 2)),
    ("#3, #1", ConnectionPair(3, 1)),
])
def test_a_query_is_a_rule_a_family_a_severity_or_two_connections(text, wanted):
    assert parse_query(text) == wanted


@pytest.mark.parametrize(("text", "words"), [
    ("PW-NOPE", "unknown rule 'PW-NOPE'"),
    ("PW-PAI", "unknown rule 'PW-PAI'"),  # a family ends at a dash
    ("2 2", "#2 twice"),
    ("1 2 3", "unknown rule"),
    ("", "type a rule id"),
])
def test_what_does_not_read_is_one_line(text, words):
    with pytest.raises(BisectError, match=words):
        parse_query(text)


# -- to the first violation --------------------------------------------------------------------------


@pytest.mark.slow
async def test_a_rule_id_jumps_to_its_first_frame_whatever_the_cursor():
    async with loaded_app(SAMPLES / "violations.mcap") as (app, pilot):
        store = app.model.store
        wanted = next(n for n in store.violating
                      if any(v.rule_id == "PW-PAIR-UNANSWERED" for v in store.violations[n]))
        await pilot.press("G")  # from the end: the first frame, not the next one
        await ask(pilot, "PW-PAIR-UNANSWERED")
        await until(pilot, lambda: not isinstance(app.screen, BisectPrompt), "the search")
        assert app.frames.frame == wanted
        assert any(v.rule_id == "PW-PAIR-UNANSWERED" for v in store.violations[app.frames.frame])
        assert not any(v.rule_id == "PW-PAIR-UNANSWERED" for n in store.violating if n < wanted
                       for v in store.violations[n])
        await pilot.pause()
        assert app.detail.frame == wanted


@pytest.mark.slow
async def test_a_severity_and_a_filter_are_honoured():
    async with loaded_app(SAMPLES / "violations.mcap") as (app, pilot):
        store = app.model.store
        await ask(pilot, "warning")
        await until(pilot, lambda: not isinstance(app.screen, BisectPrompt), "the search")
        warnings = [n for n in store.violating if any(v.severity == Severity.WARNING for v in store.violations[n])]
        assert app.frames.frame == warnings[0]
        await pilot.press("slash", *"dir:s2c", "enter")
        await loaded(pilot)
        await ask(pilot, "warning")
        await until(pilot, lambda: not isinstance(app.screen, BisectPrompt), "the search")
        assert app.frames.frame == next(n for n in warnings if store.direction(n) is Direction.S2C)


@pytest.mark.slow
async def test_an_unknown_rule_is_said_in_the_prompt_which_stays():
    async with loaded_app(SAMPLES / "violations.mcap") as (app, pilot):
        await pilot.press("j")
        prompt = await ask(pilot, "PW-NO-SUCH-RULE")
        await pilot.pause()
        assert app.screen is prompt
        assert said(prompt).startswith("unknown rule 'PW-NO-SUCH-RULE': type a rule id")
        prompt.query_one("#bisect-query").value = "PW-HS-ORDER"
        await pilot.press("enter")
        await until(pilot, lambda: app.screen is not prompt, "the search")
        await pilot.press("slash", *"conn:1", "enter")
        await loaded(pilot)
        prompt = await ask(pilot, "PW-HS-ORDER")
        await until(pilot, lambda: "no frame in view" in said(prompt), "the search")
        assert said(prompt) == "no frame in view has a violation of PW-HS-ORDER"
        await pilot.press("escape")
        assert app.screen is not prompt


@pytest.mark.slow
async def test_the_selected_frames_rule_is_offered():
    async with loaded_app(SAMPLES / "violations.mcap") as (app, pilot):
        store = app.model.store
        await pilot.press("n", "n")
        rule = store.violations[app.frames.frame][0].rule_id
        await pilot.press("b")
        assert app.screen.query_one("#bisect-query").value == rule
        await pilot.press(*"info")  # typing replaces what was offered
        assert app.screen.query_one("#bisect-query").value == "info"
        await pilot.press("escape", "g", "b")
        assert app.screen.query_one("#bisect-query").value == ""  # frame 0 breaks no rule


# -- to where two connections part ------------------------------------------------------------------

REQUEST = b"rr1-12--0--0-ss1"


def answer(value: int) -> bytes:
    return b"cr1-12--%d--0-ss1" % value


class ServerPerConnection(StepServer):
    """A StepServer playing the next of ``scripts`` on each new connection."""

    def __init__(self, *scripts: list[tuple]) -> None:
        super().__init__(scripts[0])
        self.scripts = list(scripts)

    async def _serve_connection(self, reader, writer) -> None:
        self.steps = self.scripts.pop(0)
        await super()._serve_connection(reader, writer)


async def sessions(path: Path, *answers: list[int]) -> Path:
    """One recorded connection per list of answers, one after the other: the
    client asks for channel 12 once per answer, the server says the value."""
    servers = [[s for v in values for s in (("recv", len(REQUEST)), ("send", answer(v)))] for values in answers]
    async with ServerPerConnection(*servers) as server, recording(server.port, str(path)) as rec:
        for values in answers:
            await play_client(rec.proxy.port,
                              [s for v in values for s in (("send", REQUEST), ("recv", len(answer(v))))])
        await asyncio.sleep(0.05)  # the last close reaches the proxy
    return path


def connection(app: WhiztapApp, conn: int) -> list[int]:
    store = app.model.store
    return [n for n in range(store.count) if store.conn[n] == conn]


@pytest.mark.slow
async def test_two_connections_part_at_a_known_frame_shown_side_by_side(tmp_path):
    path = await sessions(tmp_path / "two.mcap", [500, 501, 502, 503, 504], [500, 501, 777, 503, 504])
    async with loaded_app(path) as (app, pilot):
        first, second = connection(app, 1), connection(app, 2)
        assert len(first) == len(second) == 10
        k = first[5]  # the third answer (client, server, client, server, client, *server*)
        assert app.model.store.raw(k) == answer(502)
        await ask(pilot, "1 2")
        await until(pilot, lambda: isinstance(app.screen, DivergenceScreen), "the comparison")
        lines = str(app.screen.query_one("#divergence").render()).split("\n")
        assert lines[0] == "Connections #1 (10 frames) and #2 (10 frames) first differ at server frame 3"
        rows = [line for line in lines if "│" in line][1:]
        assert len(rows) == 9  # four before, the difference, four after
        marked = [row for row in rows if row.startswith("▶")]
        assert len(marked) == 1 and rows.index(marked[0]) == 4
        left, right = marked[0].split("│")
        assert "← response" in left and "cr1-12--502--0-ss1" in left and "cr1-12--777--0-ss1" in right
        same = [row for row in rows if row.startswith("  ")]
        assert len(same) == 8 and all(row.split("│")[0][13:].strip() == row.split("│")[1][11:].strip()
                                      for row in same)
        assert "#1: cr1-12--502--0-ss1" in lines and "#2: cr1-12--777--0-ss1" in lines
        await pilot.press("escape")
        assert not isinstance(app.screen, DivergenceScreen)
        assert app.frames.frame == k and app.frames.has_focus


@pytest.mark.slow
async def test_a_connection_that_goes_on_differs_where_the_other_ended(tmp_path):
    path = await sessions(tmp_path / "longer.mcap", [500, 501], [500, 501, 502], [500, 501])
    async with loaded_app(path) as (app, pilot):
        await ask(pilot, "1 2")
        await until(pilot, lambda: isinstance(app.screen, DivergenceScreen), "the comparison")
        text = str(app.screen.query_one("#divergence").render())
        assert "first differ at client frame 3" in text
        [marked] = [line for line in text.split("\n") if line.startswith("▶")]
        assert marked.split("│")[0].strip() == "▶ (no frame)" and "rr1-12--0--0-ss1" in marked.split("│")[1]
        await pilot.press("escape")
        assert app.frames.frame == connection(app, 2)[4]  # A has no frame there: B's
        prompt = await ask(pilot, "1 3")
        await until(pilot, lambda: "same frames" in said(prompt), "the comparison")
        assert said(prompt) == "connections #1 and #3 carry the same frames"
        prompt.query_one("#bisect-query").value = "1 9"
        await pilot.press("enter")
        await until(pilot, lambda: "no frame" in said(prompt), "the comparison")
        assert said(prompt) == "connection #9 has no frame here"


# -- the replay screen's faults ------------------------------------------------------------------------

LATE = "drop dir:s2c kind:response ch:13 nth:1"


@pytest.fixture(scope="module")
def faulted(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Sensor Requests on channels 12 and 13, recorded through a proxy dropping every second answer on 12."""
    path = tmp_path_factory.mktemp("tui-replay-faults") / "faulted.mcap"
    asyncio.run(record(path, MiddleSettings(faults=(parse_fault(DROP),))))
    return path


async def replayed(path: Path, faults: str, specs: str = "") -> ReplayScreen:
    """The replay screen's run of ``path`` against a fresh simulator, in
    lockstep, under ``faults`` (none, recording, typed with ``specs``)."""
    async with simulator() as sim, loaded_app(path) as (app, pilot):
        await pilot.press("r")
        screen = app.screen
        assert isinstance(screen, ReplayScreen)
        screen.query_one("#target").value = f"{LOCAL}:{sim.port}"
        screen.query_one("#pace").value = "lockstep"
        screen.query_one("#faults").value = faults
        await pilot.pause()
        screen.query_one("#fault-specs").value = specs
        await pilot.press("f5")
        await until(pilot, lambda: screen.runner.done, "the replay")
        await until(pilot, lambda: screen.comparisons.rows == len(screen.runner.comparisons))
        await pilot.pause(0.2)
        screen.status = str(screen.query_one("#replay-status").render())
        screen.faults_said = str(screen.comparisons.border_subtitle or "")
    return screen


def statuses(screen: ReplayScreen) -> list[tuple[str, bytes | None]]:
    return [(str(c.status), c.request) for c in screen.runner.comparisons if not c.match]


@pytest.mark.slow
async def test_the_recordings_faults_drop_the_same_answers_again(faulted):
    screen = await replayed(faulted, "recording")
    runner = screen.runner
    assert runner.state == "finished" and runner.options.faults == (parse_fault(DROP),)
    assert statuses(screen) == [("missing", b"rr1-12--0--0-ss1")] * (ROUNDS // 2)
    assert f"{ROUNDS // 2} missing" in screen.status and "FINISHED" in screen.status
    assert screen.faults_said == f"through faults: {DROP}"


@pytest.mark.slow
async def test_by_default_no_fault_is_applied_and_every_answer_comes(faulted):
    screen = await replayed(faulted, "none", specs=LATE)  # typed but not chosen: not applied
    assert screen.runner.options.faults == () and statuses(screen) == []
    assert len(screen.runner.comparisons) == 2 * ROUNDS and f"{2 * ROUNDS} match" in screen.status
    assert screen.faults_said == ""


@pytest.mark.slow
async def test_typed_faults_apply_instead_of_the_recordings(faulted):
    screen = await replayed(faulted, "typed", specs=f"{LATE} ; delay:1ms dir:c2s")
    assert [f.text for f in screen.runner.options.faults] == [LATE, "delay:1ms dir:c2s"]
    assert statuses(screen) == [("missing", b"rr1-13--0--0-ss1")]


@pytest.mark.slow
async def test_a_typed_spec_that_does_not_read_is_said_on_its_field():
    async with loaded_app(SAMPLES / "vpn.mcap") as (app, pilot):
        await pilot.press("r")
        screen = app.screen
        specs = screen.query_one("#fault-specs")
        assert specs.disabled
        screen.query_one("#target").value = f"{LOCAL}:{closed_port()}"
        await pilot.press("f5")  # a replay that ends at once, its end on the screen
        await until(pilot, lambda: screen.runner.done, "the failure")
        failed = screen.runner
        screen.query_one("#faults").value = "typed"
        await pilot.pause()
        assert not specs.disabled and specs.has_focus
        specs.value = "drop dir:s2c; drop bogus:1"
        await pilot.press("f5")
        await pilot.pause(0.3)  # a few ticks: the message stays
        assert screen.runner is failed and specs.has_class("-invalid")
        assert "unknown word 'bogus:1'" in str(specs.border_subtitle)
        assert "faults: unknown word 'bogus:1'" in str(screen.query_one("#replay-status").render())
        await pilot.press("backspace")
        assert not specs.has_class("-invalid") and specs.border_subtitle is None


@pytest.mark.parametrize(("text", "specs"), [
    ("drop dir:s2c", ["drop dir:s2c"]),
    (" drop dir:s2c ;delay:2ms ; ", ["drop dir:s2c", "delay:2ms"]),
    ("replace:'a;b' nth:1; dup", ["replace:'a;b' nth:1", "dup"]),
    ('replace:"a\\";b" ; dup', ['replace:"a\\";b"', "dup"]),
    ("replace:'open; dup", ["replace:'open; dup"]),  # parse_fault names the open quote
])
def test_specs_split_at_semicolons_outside_quotes(text, specs):
    assert split_specs(text) == specs
