"""With the proxy in the middle, the password shows in no output, whatever
the proxy does to the traffic (issue 25, item 3).

Every output is in one registry (tests/outputs.py), held to the code's own
lists by ``test_every_output_is_registered``.  The property drives the
middle's sans-IO core through the controller on a fake clock
(tests/middle_drive.py: no socket, so many examples are cheap): an eager
password (sent before ``sendchkpass``), one split over reads, one with no line
break (run into by a command, or alone), and a wrong one, through every action
(drop, dup, delay, corrupt, replace, slice, bandwidth, blackhole, reset,
close, intercept with release, edit and drop, inject), and looks for any 8
bytes of it, as text and base64, in everything told to the consumers as the
recording, the live TUI and Foxglove get it, every answer of the control API
and ``whiztap ctl``'s lines for it, the proxy's warnings and a script that
prints everything it can see of each frame.  One recording of every shape
under every action is then read by every registered reader; one real
``whiztap record --control --foxglove --script`` run and one live TUI cover
the outputs that need a process.

The rule is the recorder's (docs/recording-format.md, *Passwords*): in a
session whose server begins with ``sendchkpass``, the client's first line, up
to its line break or a frame that completes after it, is the password.
"""

from __future__ import annotations

import asyncio
import json
import re
import threading
import types
import urllib.request
from pathlib import Path

import click
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from whiztap.analyzer.protocol.examples import CONFIG
from whiztap.analyzer.recording.format import metadata_record
from whiztap.analyzer.traffic import Action, Intervention
from whiztap.sniffer.mitm import http_api
from whiztap.sniffer.mitm.scripts import load_script
from whiztap.sniffer.mitm.controller import middle_metadata
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile

from tests.middle_drive import C2S, MS, S2C, T0, Drive
from tests.middle_support import Raw
from tests.cli_support import run_cli, start_process
from tests.record_support import CONTROL_TOKEN, LOCAL, WAIT, RecordProcess, StepServer, play_client, read_all
from tests.outputs import (
    API_OUTPUTS,
    FILE_COMMANDS,
    FILE_OUTPUTS,
    FLOW_VIEW,
    LOGGING_SCRIPT,
    NOT_OUTPUTS,
    QUICK_FILE_OUTPUTS,
    SECRET,
    MIRROR_ONLY,
    TRAFFIC_TOPICS,
    api_text,
    assert_no_leak,
    leaks,
    route_key,
    route_text,
    script_log,
    store_text,
)

COMMAND, ANSWER = b"rr1-24--0--0-ss1", CONFIG
SENSOR, SENSOR_ANSWER = b"rr1-12--0--0-ss1", b"cr1-12--5--0-ss1"
ASKS, YES, NO = b"sendchkpass", b"readytogo", b"Failed Validation"

# The actions, each as a fault SPEC that may choose the password's frame (or the line break next to it).
FAULT_ACTIONS = ("drop", "dup", "delay:40ms", "delay:2s", "corrupt", 'replace:"rr1-13--0--0-ss1"', "slice:3",
                 "bandwidth:1kB/s", "blackhole", "reset", "close")
CHOOSERS = ("dir:c2s", "dir:c2s nth:1", "dir:c2s nth:2", "dir:c2s every:2", "", "dir:c2s kind:unframed")
SHAPES = ("eager", "eager, no line break", "eager, then a pause", "split", "no line break, then a command",
          "no line break, alone", "wrong")


# -- the sessions -------------------------------------------------------------------------------------


def _cut(draw, data: bytes) -> list[bytes]:
    """``data`` in random reads."""
    cuts = sorted(draw(st.lists(st.integers(1, max(len(data) - 1, 1)), max_size=4)))
    return [data[a:b] for a, b in zip([0, *cuts], [*cuts, len(data)]) if b > a]


def login(shape: str, lead: bytes, cut=lambda data: [data]) -> list[tuple]:
    """One Winsock login of ``shape`` as steps: ("c", bytes) the client sends,
    ("s", bytes) the server sends, ("t", ns) time passes; ``lead``: line
    breaks before the password; ``cut``: the client's bytes into reads."""
    def c(data):
        return [("c", piece) for piece in cut(data)]

    if shape == "eager":
        return [*c(lead + SECRET + b"\r\n" + COMMAND), ("s", ASKS), ("s", YES), ("s", ANSWER)]
    if shape == "eager, no line break":
        return [*c(lead + SECRET + COMMAND), ("s", ASKS), ("s", YES), ("s", ANSWER)]
    if shape == "eager, then a pause":  # the password passes on untouched once it stalls
        return [*c(lead + SECRET), ("t", 300 * MS), ("s", ASKS), ("c", b"\r\n"), ("s", YES), ("c", SENSOR),
                ("s", SENSOR_ANSWER)]
    if shape == "split":
        return [("s", ASKS), *[("c", bytes([b])) for b in lead + SECRET], ("c", b"\r\n"), ("s", YES), ("c", SENSOR),
                ("s", SENSOR_ANSWER)]
    if shape == "no line break, then a command":
        return [("s", ASKS), *c(lead + SECRET + COMMAND), ("s", YES), ("s", ANSWER)]
    if shape == "no line break, alone":
        return [("s", ASKS), *c(lead + SECRET), ("t", 300 * MS), ("s", YES), ("c", SENSOR), ("s", SENSOR_ANSWER)]
    assert shape == "wrong"
    return [("s", ASKS), *c(lead + SECRET + b"\r\n"), ("s", NO), ("c", SENSOR)]


PEOPLE = ("release", "edit", "drop", "wait", "release-all")
ENDS = ("both FIN", "the client resets", "the server goes", "both go at once")


@st.composite
def sessions(draw):
    """A login, faults in force, interception or not, injections and what a
    person does with held frames, and how the connection ends."""
    shape = draw(st.sampled_from(SHAPES))
    steps = login(shape, draw(st.sampled_from([b"", b"\r\n"])), lambda data: _cut(draw, data))
    for _ in range(draw(st.integers(0, 3))):  # time passes anywhere: delays end, stalls pass raw
        steps.insert(draw(st.integers(0, len(steps))), ("t", draw(st.sampled_from([MS, 50 * MS, 250 * MS]))))
    for _ in range(draw(st.integers(0, 2))):
        way = draw(st.sampled_from(["c2s", "s2c"]))
        frame = "sensor 12" if way == "c2s" else SENSOR_ANSWER.decode()
        steps.insert(draw(st.integers(0, len(steps))), ("inject", way, frame))
    faults = [f"{draw(st.sampled_from(FAULT_ACTIONS))} {draw(st.sampled_from(CHOOSERS))}".strip()
              for _ in range(draw(st.integers(0, 2)))]
    intercept = draw(st.sampled_from([None, None, "dir:c2s", "dir:c2s kind:unframed", "unframed", ""]))  # "": all
    people = draw(st.lists(st.sampled_from(PEOPLE), min_size=1, max_size=6))
    end = draw(st.sampled_from(ENDS))  # at the end, or anywhere after the first step (a frame may be due later)
    steps.insert(draw(st.integers(1, len(steps))), ("end", end))
    return shape, steps, faults, intercept, people


# -- driving the middle -----------------------------------------------------------------------------------


def _act_on_held(drive: Drive, people: list[str], turn: int) -> None:
    """A person looks at the held frames and does what ``people`` says, in turn."""
    _, answer = drive.api("GET", "/held")
    for held in answer["held"]:
        what = people[turn % len(people)]
        turn += 1
        if what == "release":
            drive.api("POST", f"/held/{held['id']}/release", {})
        elif what == "edit":
            edit = "sensor 13" if held["dir"] == "c2s" else SENSOR_ANSWER.decode()
            drive.api("POST", f"/held/{held['id']}/release", {"edit": edit, "force": True})
        elif what == "drop":
            drive.api("POST", f"/held/{held['id']}/drop")
        elif what == "release-all":
            drive.api("POST", "/held/release-all")


def _end(drive: Drive, conn: int, end: str) -> None:
    if end == "both FIN":
        drive.fin(conn, C2S)
        drive.fin(conn, S2C)
        drive.advance(100 * MS)
        drive.lose(conn, C2S)
        drive.lose(conn, S2C)
    elif end == "the client resets":
        drive.lose(conn, C2S)
        drive.lose(conn, S2C)
    elif end == "the server goes":
        drive.lose(conn, S2C)
        drive.advance(10 * MS)
        drive.lose(conn, C2S)
    else:
        drive.close(conn)


def drive_session(drive: Drive, session, conn: int = 1) -> None:
    """Play ``session`` (from ``sessions()``) on connection ``conn`` of
    ``drive``, its faults and interception aimed at it (``conn:N``), and take
    them away once it is over."""
    _, steps, faults, intercept, people = session
    ids = []
    for spec in faults:
        status, answer = drive.api("POST", "/faults", {"spec": f"{spec} conn:{conn}"})
        assert status == 201, answer
        ids.append(answer["id"])
        drive.api("POST", f"/faults/{ids[-1]}/enable", {"enabled": False})
        drive.api("POST", f"/faults/{ids[-1]}/enable", {"enabled": True})
    if intercept is not None:
        drive.api("PUT", "/intercept", {"filter": f"{intercept} conn:{conn}"})
    drive.open(conn)
    for turn, step in enumerate(steps):
        if step[0] == "c":
            drive.send(conn, C2S, step[1])
        elif step[0] == "s":
            drive.send(conn, S2C, step[1])
        elif step[0] == "t":
            drive.advance(step[1])
        elif step[0] == "end":
            _end(drive, conn, step[1])
        else:
            drive.api("POST", "/inject", {"conn": conn, "dir": step[1], "frame": step[2], "force": True})
        drive.advance(MS)
        drive.every_get()
        if intercept is not None:
            _act_on_held(drive, people, turn)
    if "wait" in people:
        drive.settle()  # what nobody let go times out
    drive.every_get()
    drive.settle()
    drive.every_get()
    for fault_id in ids:
        drive.api("DELETE", f"/faults/{fault_id}")
    drive.api("PUT", "/intercept", {"filter": ""})


# -- what the consumers make of the events --------------------------------------------------------------


def record(path: Path, drive: Drive, keep_secrets: bool = False) -> Path:
    """The events the middle told, through the real recorder into ``path``."""
    metadata = metadata_record(source="proxy", secrets="kept" if keep_secrets else "redacted",
                               **middle_metadata([], 1))
    recorder = Recorder(RecordingFile(str(path), metadata), keep_secrets=keep_secrets)
    recorder.start(T0)
    for event in drive.events:
        recorder.receive(event)
    recorder.stop(drive.t + MS)
    return path


def live_tui(drive: Drive, redact: bool = True) -> bytes:
    """What the live TUI holds once the events went through its source (masked as the file is)."""
    from whiztap.tui.data.model import TrafficModel
    from whiztap.tui.data.sources import LiveSource

    source = LiveSource(None, "live", redact_passwords=redact)
    source.recording = types.SimpleNamespace(controller=drive.controller)
    source.queue.extend(drive.events)
    source.stopped.set()
    model = TrafficModel("live", redact_passwords=redact)
    source.feed(model, threading.Event())
    return store_text(model)


def in_memory_outputs(drive: Drive, script=None) -> list[tuple[str, str | bytes]]:
    """Every output that needs no file: the API's answers and ctl's lines for
    them, the proxy's warnings, the script's log and the interventions as told."""
    shown: list[tuple[str, str | bytes]] = []
    for method, path, status, answer in drive.answers:
        shown.append((f"{method} {path} ({status})", api_text(method, path, answer)))
    shown.append(("the proxy's warnings", "\n".join(drive.reports)))
    if script is not None:
        shown.append(("a script's log lines", script_log(script)))
    for event in drive.events:
        if isinstance(event, Intervention):
            shown.append((f"the intervention {event.action} as told", event.before + b"|" + event.after))
    return shown


@pytest.fixture(scope="module")
def logging_script(tmp_path_factory):
    path = tmp_path_factory.mktemp("script") / "logs_every_flow.py"
    path.write_text(LOGGING_SCRIPT)
    return path


def _drive_with_script(script_path: Path) -> tuple[Drive, object]:
    """A drive whose controller runs the logging script (quiet: its log is read from the module)."""
    drive = Drive()
    script = load_script(script_path)
    script.module.PRINT = False
    drive.controller.add_script(script)
    return drive, script


# Bytes the middle puts before the password (an injection, a line break before it replaced or
# edited into a frame) once unmasked it in /tcp/delivered: the core masked what it delivered by
# the rule over what the server received, which then no longer began with the client's line.
# Now what the server receives is masked by the rule over what the client sent.
_FOREIGN = {Action.INJECT, Action.EDIT, Action.REPLACE}


def foreign_before_the_password(drive: Drive, conn: int = 1) -> bool:
    """Bytes the client did not send reached the server before some of its password did."""
    got = drive.delivered(conn, C2S)
    pieces = [SECRET[i:i + 3] for i in range(len(SECRET) - 2)]
    return any(e.conn == conn and e.direction is C2S and e.action in _FOREIGN and e.delivered >= 0
               and any(piece in got[e.delivered:] for piece in pieces)
               for e in drive.events if isinstance(e, Intervention))


# Found by the property: bytes a lane passed on raw (an eager password that
# stalled) behind a frame delayed past the close were recorded in clear as expired.
RAW_BEHIND_A_DELAY = ("eager, then a pause", [("c", b"\r\nKx9hunter2Tq4"), ("t", 300 * MS), ("s", ASKS),
                                              ("c", b"\r\n" + COMMAND), ("end", "the server goes")],
                      ["delay:2s dir:c2s nth:1"], None, ["release"])


@pytest.mark.slow
@settings(max_examples=60, deadline=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(session=sessions())
@example(session=RAW_BEHIND_A_DELAY)
def test_no_action_of_the_middle_puts_the_password_in_any_output(tmp_path_factory, logging_script, session):
    drive, script = _drive_with_script(logging_script)
    drive_session(drive, session)
    for where, text in in_memory_outputs(drive, script):
        assert_no_leak(where, text)
    assert_no_leak("the live TUI", live_tui(drive))
    path = record(tmp_path_factory.mktemp("property") / "r.mcap", drive)
    for name in QUICK_FILE_OUTPUTS:
        assert_no_leak(name, FILE_OUTPUTS[name](path))


@pytest.mark.parametrize("session", [
    ("split", [("s", ASKS), ("inject", "c2s", "sensor 12"), ("c", SECRET), ("c", b"\r\n"), ("s", YES)],
     [], None, ["release"]),
    ("eager", [("c", b"\r\n"), ("c", SECRET + b"\r\n"), ("s", ASKS), ("s", YES)],
     ['replace:"rr1-13--0--0-ss1" dir:c2s nth:1'], None, ["release"]),
    ("eager", [("c", b"\r\n"), ("c", SECRET + b"\r\n"), ("s", ASKS), ("s", YES)], [], "dir:c2s kind:eol", ["edit"]),
], ids=["an injection", "a line break replaced by a frame", "a line break edited into a frame"])
def test_bytes_the_middle_puts_before_a_password_leave_it_masked(tmp_path, session):
    drive = Drive()
    drive_session(drive, session)
    assert foreign_before_the_password(drive)
    path = record(tmp_path / "r.mcap", drive)
    assert_no_leak("every topic", FILE_OUTPUTS["every topic"](path))


# -- one recording of every shape under every action, through every reader ---------------------------

CASES = [(shape, action) for shape in SHAPES
         for action in (*FAULT_ACTIONS, "delay:2s nth:1", "intercept release", "intercept edit",
                        "intercept drop", "intercept release-all", "inject c2s", "inject s2c")]


def case_session(shape: str, action: str, n: int) -> tuple:
    """``shape`` under ``action``, the password's reads cut in two, a line break before it every other time."""
    late = "2s" in action  # a line break delayed past the close, the password behind it
    steps = login(shape, b"\r\n" if n % 2 or late else b"",
                  lambda data: [data[:5], data[5:]] if len(data) > 5 else [data])
    faults, intercept, people = [], None, ["wait"]
    if action.startswith("intercept"):
        intercept, people = "dir:c2s", [action.split()[1]]
    elif action.startswith("inject"):
        way = action.split()[1]
        at = len(steps) // 2
        steps.insert(at, ("inject", way, "sensor 12" if way == "c2s" else SENSOR_ANSWER.decode()))
    else:
        faults = [action if "dir:" in action else f"{action} dir:c2s"]
    steps.append(("end", "the server goes" if late else ENDS[n % len(ENDS)]))
    return shape, steps, faults, intercept, people


@pytest.fixture(scope="module")
def every_case(tmp_path_factory, logging_script):
    """Every case of CASES as a connection of its own, one after the other;
    the drive, the script, and the recording the recorder made of it."""
    drive, script = _drive_with_script(logging_script)
    for n, (shape, action) in enumerate(CASES, 1):
        drive_session(drive, case_session(shape, action, n), conn=n)
    path = record(tmp_path_factory.mktemp("every") / "every.mcap", drive)
    return drive, script, path


@pytest.mark.slow
@pytest.mark.parametrize("output", sorted(FILE_OUTPUTS))
def test_no_reader_of_a_recording_made_in_the_middle_shows_the_password(every_case, output):
    _, _, path = every_case
    assert_no_leak(output, FILE_OUTPUTS[output](path))


@pytest.mark.slow
def test_nothing_else_the_middle_said_shows_the_password(every_case):
    drive, script, _ = every_case
    for where, text in in_memory_outputs(drive, script):
        assert_no_leak(where, text)
    assert_no_leak("the live TUI", live_tui(drive))


def test_the_cases_reach_every_action_topic_and_route(every_case):
    """The recording of every case holds every action, every traffic topic,
    and the drive asked every route of the control API: nothing registered went unread."""
    drive, script, path = every_case
    by_topic = read_all(str(path))
    wanted = set(TRAFFIC_TOPICS) - set(MIRROR_ONLY)  # a recording with --mirror: tests/test_mirror.py
    assert wanted <= set(by_topic), wanted - set(by_topic)
    done = {i["action"] for i in by_topic["/interventions"]}
    wanted = {a.split(":")[0] for a in FAULT_ACTIONS} | {"hold", "release", "edit", "drop", "inject", "expire"}
    assert wanted <= done, wanted - done
    asked = {(method, path_) for method, path_, _, _ in drive.answers}
    assert {route_key(m, p) for m, p in asked} == set(API_OUTPUTS)
    assert any(line.startswith("channel=") for line in script.module.LOG)
    # kept secrets are kept: the check can fail
    kept = Drive(redact=False)
    drive_session(kept, case_session("eager", "intercept edit", 1))
    assert leaks(json.dumps([a for *_, a in kept.answers]) + repr(kept.events))


# -- the registry is complete ----------------------------------------------------------------------------


def _choices(command: click.Command, option: str) -> list[str]:
    [param] = [p for p in command.params if p.name == option]
    return list(param.type.choices)


def test_every_output_is_registered():
    """A format, a topic, a route, a ctl subcommand, a command or a Flow
    attribute added without its reader in tests/outputs.py fails here."""
    from importlib.metadata import entry_points

    from whiztap.analyzer.cli.analyze import analyze_command
    from whiztap.analyzer.cli.cat import cat_command
    from whiztap.analyzer.cli.info import info_command
    from whiztap.sniffer.cli.ctl import ctl_command

    for name, command in (("analyze", analyze_command), ("cat", cat_command), ("info", info_command)):
        for fmt in _choices(command, "fmt"):
            assert f"{name} --format {fmt}" in FILE_OUTPUTS, f"{name} --format {fmt} has no reader in tests/outputs.py"
    routes = {(method, route_text(pattern.pattern)) for method, pattern, _ in http_api.ROUTES}
    assert routes == set(API_OUTPUTS), routes ^ set(API_OUTPUTS)
    shown = {name for names, _ in API_OUTPUTS.values() for name in names}
    subcommands = {f"{name} {sub}" if isinstance(command, click.Group) else name
                   for name, command in ctl_command.commands.items()
                   for sub in (command.commands if isinstance(command, click.Group) else [""])}
    assert subcommands == shown, subcommands ^ shown
    commands = {e.name for e in entry_points(group="whiztap.commands")}
    assert commands == set(NOT_OUTPUTS) | FILE_COMMANDS, commands ^ (set(NOT_OUTPUTS) | FILE_COMMANDS)
    for name in FILE_COMMANDS:
        assert any(key.split()[0] == name for key in FILE_OUTPUTS), name
    assert FLOW_VIEW and "raw" in FLOW_VIEW and "text" in FLOW_VIEW and "meaning" in FLOW_VIEW


# -- the outputs that need a process: whiztap record, ctl, Foxglove live, the TUI ---------------------------


async def _ctl(control: str, *args: str) -> str:
    """``whiztap ctl`` as a user runs it; what it printed (it must not fail)."""
    done = await asyncio.to_thread(run_cli, "ctl", "--control", control, "--control-token", CONTROL_TOKEN, *args)
    assert done.returncode == 0, done.stderr
    return done.stdout + done.stderr


async def _get(url: str) -> str:
    request = urllib.request.Request(url, headers={"Authorization": f"Bearer {CONTROL_TOKEN}"})
    return await asyncio.to_thread(lambda: urllib.request.urlopen(request, timeout=10).read().decode())


@pytest.mark.slow
async def test_whiztap_record_in_the_middle_shows_the_password_nowhere(tmp_path, logging_script):
    """An eager client's password held by an interception, listed, released,
    duplicated and delayed by faults, through ``whiztap record --control
    --foxglove --script``: not on its terminal, not in ctl's lines or the
    API's answers while it is held, not on Foxglove live, not in the file."""
    from tests.test_foxglove_live import FoxgloveClient, until  # it imports the TUI

    path = tmp_path / "e2e.mcap"
    server = StepServer([("recv", len(SECRET) + 2), ("send", ASKS), ("send", YES), ("recv", len(SENSOR)),
                         ("send", SENSOR_ANSWER)])
    async with server:
        proc = await start_process(
            "record", "--listen", "127.0.0.1:0", "--upstream", f"{LOCAL}:{server.port}", "-o", path,
            "--control", "127.0.0.1:0", "--control-token", CONTROL_TOKEN, "--foxglove", "127.0.0.1:0",
            "--script", str(logging_script),
            "--fault", "dup dir:c2s nth:1", "--fault", "delay:5ms dir:c2s")
        rec = RecordProcess(proc)
        first = (await asyncio.wait_for(proc.stdout.readline(), WAIT)).decode()
        m = re.search(r"recording 127\.0\.0\.1:(\d+) -> .*foxglove: (ws://\S+), control: http://(\S+) ", first)
        assert m, first
        rec.port, fox_url, control = int(m.group(1)), m.group(2), m.group(3)
        fox = await FoxgloveClient.connect(fox_url)
        await asyncio.wait_for(fox.subscribed.wait(), WAIT)  # the middle's topics too, before any traffic
        assert {"/tcp/delivered", "/interventions"} <= set(fox.topics())
        shown = [first]
        shown.append(await _ctl(control, "intercept", "dir:c2s"))
        client = asyncio.create_task(play_client(rec.port, [("send", SECRET + b"\r\n"), ("recv", len(ASKS + YES)),
                                                             ("send", SENSOR), ("recv", len(SENSOR_ANSWER))]))
        while True:  # each held frame listed, then let go
            held = json.loads(await _ctl(control, "--format", "json", "held"))["held"]
            shown += [await _ctl(control, "held"), await _ctl(control, "state"), await _get(f"http://{control}/held"),
                      await _get(f"http://{control}/state"), await _get(f"http://{control}/connections")]
            if held:
                shown.append(await _ctl(control, "release", str(held[0]["id"])))
            elif len(server.received) >= len(SECRET) + 2:
                break
            await asyncio.sleep(0.02)
        shown.append(await _ctl(control, "intercept", "--off"))
        got = await asyncio.wait_for(client, WAIT)
        assert got == ASKS + YES + SENSOR_ANSWER
        assert bytes(server.received).startswith(SECRET + SECRET + b"\r\n")  # the dup fault acted on the password
        await until(lambda: "/tcp/delivered" in fox.got and "/interventions" in fox.got, "the middle's topics, live")
        assert not fox.refused_at_start()  # no subscription refused
        await fox.close()
        code, out, err = await rec.finish()
    assert code == 0, err
    assert "Traceback" not in err
    assert_no_leak("whiztap record's terminal", out + err)
    for n, text in enumerate(shown):
        assert_no_leak(f"ctl or the API (answer {n})", text)
    assert any("redacted" in text for text in shown)  # the held password was listed, masked
    foxglove = "\n".join(f"{topic} {payload.decode('latin-1')}" for topic, got_ in fox.got.items()
                         for _, payload in got_)
    assert_no_leak("Foxglove live", foxglove)
    assert "channel=" in out  # the script's log lines are on the terminal
    for name, read in FILE_OUTPUTS.items():
        assert_no_leak(name, read(path))


@pytest.mark.slow
async def test_the_live_tui_shows_a_held_password_masked_in_its_row_and_its_editor(tmp_path):
    """The screen itself (a real app, through Pilot): the held row, the
    detail pane and the editor opened on it show the password masked."""
    from tests.tui_support import SIZE, until
    from whiztap.sniffer.record.record_run import RecordSettings
    from whiztap.tui.app import WhiztapApp
    from whiztap.tui.middle.editor import EditorScreen
    from whiztap.tui.data.sources import LiveSource, ProxyRig

    server = StepServer([("recv", len(SECRET) + 2), ("send", ASKS), ("send", YES)])
    async with server:
        settings = RecordSettings((LOCAL, 0), (LOCAL, server.port), str(tmp_path / "live.mcap"), quiet=True)
        app = WhiztapApp(LiveSource(ProxyRig(settings), "live"))
        async with app.run_test(size=SIZE) as pilot:
            source = app.source
            await until(pilot, lambda: source.recording is not None and source.recording.proxy is not None, "proxy")
            source.controller.set_intercept("dir:c2s")
            raw = await Raw.open(source.recording.proxy.port)
            await raw.send(SECRET + b"\r\n")
            await until(pilot, lambda: app.frames.held_frame is not None, "the held password under the cursor")
            await pilot.pause()
            screens = [app.export_screenshot()]
            edited = []
            for keys in (["e"], ["up", "e"]):  # the held line break, then the password held before it
                await pilot.press(*keys)
                await until(pilot, lambda: isinstance(app.screen, EditorScreen), "the editor")
                await pilot.pause()
                screens.append(app.export_screenshot())
                edited.append(app.screen.typed_input.value)
                await pilot.press("escape")
                await until(pilot, lambda: not isinstance(app.screen, EditorScreen), "the editor to close")
            assert "*" * len(SECRET) in edited  # the editor opened on the password, masked
            source.controller.set_intercept("")
            source.controller.release_all()
            assert await raw.take(2) == [ASKS, YES]
            await until(pilot, lambda: app.frames.held_frame is None and app.model.store.count >= 3, "the frames")
            screens.append(app.export_screenshot())
            await raw.close()
            await pilot.press("q")
            await until(pilot, lambda: not app.is_running, "the app to quit")
    for n, screen in enumerate(screens):
        assert_no_leak(f"the TUI's screen ({n})", screen)
