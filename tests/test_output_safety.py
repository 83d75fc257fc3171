"""Files the user did not ask to lose, and text from files and the wire shown,
never obeyed.

One rule for every command that writes a file: never over one of its inputs
(even with --force; the same file by another name, through a symbolic or hard
link, a relative path, or as one part of a split recording), and never over
an existing file unless --force.  Standard output and devices are always fine.

Every value taken from a recording or the wire is escaped in every text
output: no raw control character reaches a terminal, the Markdown and HTML
reports hold no live HTML, JUnit parses, and the TUI shows markup literally.
"""

from __future__ import annotations

import asyncio
import html.parser
import json
import os
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from markdown_it import MarkdownIt
from rich.console import Console
from whiztap.analyzer.protocol.observations import Direction
from whiztap.analyzer.protocol.text import escape
from whiztap.analyzer.traffic import (
    Closed,
    Data,
    Opened,
    UpstreamConnected,
    UpstreamFailed,
)
from whiztap.sniffer.record.metadata import base_metadata
from whiztap.sniffer.record.recorder import Recorder
from whiztap.sniffer.record.writer import RecordingFile
from whiztap.sniffer.sim.simulator import Simulator
from whiztap.tui.app import WhiztapApp
from whiztap.tui.widgets.detail import describe_frame
from whiztap.tui.screens.replay_screen import ReplayScreen
from whiztap.tui.data.sources import FileSource

from tests.cli_support import Ran, run_cli, run_process_async
from tests.report_page import page_data
from tests.record_support import (
    LOCAL,
    EchoServer,
    RecordProcess,
    closed_port,
    read_all,
)
from tests.test_capture import C2S, S2C, _session, _write
from tests.test_split_recordings import split_vpn_session
from tests.tui_support import SIZE, loaded, settled, until

SAMPLE = Path(__file__).parent.parent / "samples" / "vpn.mcap"


def refused(result: Ran, *words: str) -> str:
    """The command said no in one line, exit status 2; the line."""
    assert result.returncode == 2, (result.returncode, result.stderr)
    assert result.stderr.count("\n") == 1 and result.stderr.startswith("whiztap: "), result.stderr
    assert "Traceback" not in result.stderr
    for word in words:
        assert word in result.stderr, result.stderr
    return result.stderr


# -- never over an input -------------------------------------------------------------------------

# Each command that reads a file and writes one: its arguments for (input, output).
WRITERS = {
    "analyze": lambda i, o: ["analyze", i, "-o", o],
    "analyze-junit": lambda i, o: ["analyze", i, "--format", "junit", "-o", o],
    "cat": lambda i, o: ["cat", i, "-o", o],
    "replay": lambda i, o: ["replay", i, "--target", f"{LOCAL}:{closed_port()}", "-o", o],
    "recover": lambda i, o: ["recover", i, "-o", o],
    "capture": lambda i, o: ["capture", "--pcap", i, "--port", "5000", "-o", o],
}


def _input_for(command: str, folder: Path) -> Path:
    """A real input of the command: a recording, or for capture a pcap."""
    if command == "capture":
        return Path(_write(folder / "in.pcap", _session([(0, C2S)], [(0, S2C)])))
    path = folder / "in.mcap"
    shutil.copy(SAMPLE, path)
    return path


# Every command as the user names the input; the other names (one helper
# checks them all) on a command that writes text and one that writes a recording.
NAMINGS = [(command, "same") for command in WRITERS] + [
    (command, named) for command in ("analyze", "replay") for named in ("relative", "symlink", "hardlink")]


@pytest.mark.parametrize("command, named", NAMINGS)
def test_no_command_writes_over_its_input_even_with_force(tmp_path, command, named):
    source = _input_for(command, tmp_path)
    before = source.read_bytes()
    output = {"same": str(source), "relative": f"./{source.name}", "symlink": tmp_path / "link",
              "hardlink": tmp_path / "hard"}[named]
    if named == "symlink":
        os.symlink(source.name, output)
    elif named == "hardlink":
        os.link(source, output)
    for force in ([], ["--force"]):
        ran = run_cli(*WRITERS[command](source.name, output), *force, cwd=tmp_path)
        line = refused(ran, "input", "even with --force")
        assert source.read_bytes() == before, (force, line)
    assert sorted(p.name for p in tmp_path.iterdir() if ".part" in p.name or "recover" in p.name) == []


@pytest.mark.parametrize("command", ["analyze", "cat", "replay"])
def test_no_part_of_a_split_input_is_written_over(tmp_path, command):
    parts = [Path(p) for p in split_vpn_session(tmp_path / "s.mcap")]
    before = [p.read_bytes() for p in parts]
    for target in parts:  # named by its first part, each part is an input
        refused(run_cli(*WRITERS[command](parts[0], target), "--force"), "input")
    assert [p.read_bytes() for p in parts] == before


def test_cat_follow_never_writes_where_the_recording_it_follows_will_be(tmp_path):
    part = tmp_path / "live.mcap.part"
    shutil.copy(SAMPLE, part)  # as a recorder leaves it: the name it will be renamed to is free
    for output in (part, tmp_path / "live.mcap"):
        refused(run_cli("cat", "--follow", part, "-o", output, "--force"), "input")
    assert not (tmp_path / "live.mcap").exists() and part.read_bytes() == SAMPLE.read_bytes()


# -- never over an existing file unless --force ---------------------------------------------------


@pytest.mark.parametrize("command", ["analyze", "analyze-junit", "cat", "recover", "capture"])
def test_an_existing_output_is_kept_unless_forced(tmp_path, command):
    source = _input_for(command, tmp_path)
    output = tmp_path / "out"
    output.write_bytes(b"an earlier file")
    refused(run_cli(*WRITERS[command](source, output)), f"{output} exists; use --force")
    assert output.read_bytes() == b"an earlier file"
    forced = run_cli(*WRITERS[command](source, output), "--force")
    assert forced.returncode in (0, 1), forced.stderr  # 1: a report with violations
    assert output.read_bytes() != b"an earlier file" and output.stat().st_size > 0
    if command not in ("analyze", "analyze-junit", "cat"):
        assert read_all(str(output))  # a whole, indexed recording


async def test_replay_keeps_an_existing_output_unless_forced(tmp_path):
    output = tmp_path / "replayed.mcap"
    output.write_bytes(b"an earlier recording")
    async with Simulator(mode="vpn") as sim:
        args = ["replay", str(SAMPLE), "--target", f"{LOCAL}:{sim.port}", "--pace", "max", "-o", str(output)]
        code, _, err = await run_process_async(*args)
        assert code == 2 and err == (f"whiztap: {output} exists; use --force to overwrite it "
                                     "or -o to choose another name\n")
        assert output.read_bytes() == b"an earlier recording"
        code, _, err = await run_process_async(*args, "--force")
    assert code in (0, 1), err
    assert read_all(str(output))


@pytest.mark.slow
def test_demo_and_the_live_tui_keep_an_existing_recording_unless_forced(tmp_path):
    output = tmp_path / "demo.mcap"
    output.write_bytes(b"an earlier demo")
    refused(run_cli("demo", "--headless", "--seconds", "0.3", "-o", output), f"{output} exists; use --force")
    refused(run_cli("tui", "--upstream", f"{LOCAL}:{closed_port()}", "-o", output), f"{output} exists; use --force")
    assert output.read_bytes() == b"an earlier demo"
    forced = run_cli("demo", "--headless", "--seconds", "0.3", "-o", output, "--force")
    assert forced.returncode == 0, forced.stderr
    assert read_all(str(output))


async def test_record_keeps_an_existing_recording_unless_forced(tmp_path):
    output = tmp_path / "r.mcap"
    output.write_bytes(b"an earlier recording")
    code, _, err = await run_process_async("record", "--upstream", f"{LOCAL}:{closed_port()}", "-o", str(output))
    assert code == 2 and "exists; use --force" in err and err.count("\n") == 1
    assert output.read_bytes() == b"an earlier recording"


async def test_client_camera_keeps_an_existing_picture_unless_forced(tmp_path):
    picture = tmp_path / "pic.jpg"
    picture.write_bytes(b"an earlier picture")
    async with Simulator(mode="vpn") as sim:
        address = f"{LOCAL}:{sim.port}"
        code, out, err = await run_process_async("client", address, "camera", "-o", str(picture))
        assert code == 2 and f"{picture} exists; use --force" in err, (out, err)
        assert picture.read_bytes() == b"an earlier picture"
        code, out, err = await run_process_async("client", address, "camera", "-o", str(picture), "--force")
    assert code == 0, (out, err)
    assert picture.read_bytes().startswith(b"\xff\xd8")  # the simulator's JPEG


def test_standard_output_and_devices_are_never_refused(tmp_path):
    for args in (["analyze", SAMPLE, "-o", "-"], ["cat", SAMPLE, "-o", "-"], ["analyze", SAMPLE, "-o", os.devnull],
                 ["cat", SAMPLE, "-o", os.devnull]):
        result = run_cli(*args)
        assert result.returncode == 0 and result.stderr == "", (args, result.stderr)


@pytest.mark.slow
async def test_the_tui_replay_never_saves_over_the_recording_or_an_existing_file(tmp_path):
    recording = tmp_path / "in.mcap"
    shutil.copy(SAMPLE, recording)
    before = recording.read_bytes()
    existing = tmp_path / "earlier.mcap"
    existing.write_bytes(b"an earlier replay")
    link = tmp_path / "link.mcap"
    link.symlink_to(recording)
    app = WhiztapApp(FileSource(str(recording)))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        await pilot.press("r")
        screen = app.screen
        assert isinstance(screen, ReplayScreen)
        screen.query_one("#target").value = f"{LOCAL}:{closed_port()}"
        for output, said in ((recording, "is an input"), (link, "is the same file as the input"),
                             (existing, "exists; choose another name")):
            screen.query_one("#output").value = str(output)
            await pilot.press("f5")
            await until(pilot, lambda said=said: any(said in n.message for n in app._notifications),
                        f"the refusal of {output.name}")
            assert screen.runner is None
    assert recording.read_bytes() == before and existing.read_bytes() == b"an earlier replay"


# -- hostile text ---------------------------------------------------------------------------------

# Terminal escapes (colour, a hyperlink, a title), markup of every output format,
# NUL, other C0 and C1 controls, DEL and a bidi override.
HOSTILE = ("\x1b[31mRED\x1b]8;;http://evil\x07\x1b]0;title\x07<script>alert(1)</script>]]>&amp;"
           "[bold]B[/bold][link=http://e]L[/link]|pipe|`tick``s\x00\x01\x08\x7f\x85\x9b\u202e")
HOSTILE_BYTES = HOSTILE.encode()
RAW_CONTROL = re.compile("[\x00-\x08\x0b-\x1f\x7f-\x9f\u202e]")  # what must never reach a terminal raw
T0 = 1_700_000_000_000_000_000


@pytest.fixture(scope="module")
def hostile(tmp_path_factory) -> Path:
    """A recording whose file name carries markup and an escape sequence too."""
    return record_hostile(tmp_path_factory.mktemp("hostile") / "evil-\x1b[2J-[bold]-<b>.mcap")


def record_hostile(path: Path) -> Path:
    """A recording made by the real recorder whose metadata values, peer
    addresses, failure details and wire bytes (both ways) carry HOSTILE."""
    metadata = base_metadata("proxy", False, "dev-sum", T0, listen=HOSTILE, upstream=HOSTILE)
    metadata.update({"host": HOSTILE, HOSTILE: HOSTILE})
    rec = Recorder(RecordingFile(str(path), metadata))
    rec.start(T0, detail=HOSTILE)
    rec.receive(Opened(1, T0 + 1, HOSTILE, HOSTILE))
    rec.receive(UpstreamConnected(1, T0 + 2, HOSTILE))
    rec.receive(Data(1, Direction.C2S, T0 + 3, b"rr1-12--0--0-ss1" + HOSTILE_BYTES + b"rr1-12--0--0-ss1"))
    rec.receive(Data(1, Direction.S2C, T0 + 4, b"cr1-12--431--0-ss1" + HOSTILE_BYTES))
    rec.receive(Closed(1, T0 + 5, "client", HOSTILE))
    rec.receive(Opened(2, T0 + 6, HOSTILE, HOSTILE))
    rec.receive(UpstreamFailed(2, T0 + 7, HOSTILE))
    rec.receive(Closed(2, T0 + 8, "server", HOSTILE))
    rec.stop(T0 + 9, HOSTILE)
    return path


def shown(text: str) -> str:
    """How a value must look on a terminal: its control characters as escapes."""
    return RAW_CONTROL.sub(lambda m: f"\\x{ord(m[0]):02x}" if ord(m[0]) < 0x100 else f"\\u{ord(m[0]):04x}", text)


def shows_no_raw_control(text: str) -> None:
    found = RAW_CONTROL.findall(text)
    assert not found, f"raw control characters reach the output: {found!r}"


@pytest.mark.parametrize("args", [
    ["info"], ["info", "--format", "json"], ["cat"], ["cat", "--format", "jsonl"], ["analyze"],
    ["analyze", "--format", "json"], ["analyze", "--format", "markdown"], ["replay", "--dry-run"], ["decode"],
], ids=lambda a: "-".join(a))
def test_no_raw_control_character_reaches_the_output(hostile, args):
    if args == ["decode"]:  # decode reads escaped text: the frames, as cat shows them
        lines = hostile.with_suffix(".txt")
        lines.write_text(f"c2s {escape(HOSTILE_BYTES)}\n")
        result = run_cli("decode", lines)
    else:
        result = run_cli(*args, hostile)
    assert result.returncode in (0, 1), result.stderr
    shows_no_raw_control(result.stdout + result.stderr)
    if args[0] in ("info", "cat", "analyze") and "--format" not in args:
        assert "\\x1b[31mRED" in result.stdout  # shown, escaped


def test_info_shows_metadata_escaped(hostile):
    result = run_cli("info", hostile)
    assert f"  host           {shown(HOSTILE)}\n" in result.stdout
    assert f"  {shown(HOSTILE)} {shown(HOSTILE)}\n" in result.stdout  # a key from the file, too
    data = json.loads(run_cli("info", "--format", "json", hostile).stdout)
    assert data["metadata"]["host"] == HOSTILE  # the JSON keeps the value exact (escaped by JSON)


def test_errors_naming_a_hostile_file_are_escaped(tmp_path):
    cut = tmp_path / "cut-\x1b[2J.mcap"
    cut.write_bytes(SAMPLE.read_bytes()[:2000])
    for args in (["analyze", cut], ["cat", cut], ["replay", cut, "--dry-run"], ["recover", cut, "-o", cut]):
        result = run_cli(*args)
        assert result.returncode == 2 and "cut-\\x1b[2J.mcap" in result.stderr, result.stderr
        shows_no_raw_control(result.stderr)
    result = run_cli("info", cut)  # says what the file is: truncated, and how to recover it
    assert "cut-\\x1b[2J.mcap" in result.stdout
    shows_no_raw_control(result.stdout + result.stderr)


def test_markdown_holds_no_live_html_and_shows_values_as_they_are(hostile):
    text = run_cli("analyze", "--format", "markdown", hostile).stdout
    page = MarkdownIt("commonmark").enable("table").render(text)  # raw HTML allowed, as on many sites
    assert "<script" not in page.lower() and "-<b>.mcap" not in page
    cells = _html_cells(page)
    frame = escape(HOSTILE_BYTES)
    assert any(frame.startswith(cell.removesuffix("…")) and len(cell) > 40 for cell in cells["code"])
    assert shown(HOSTILE) in cells["td"]  # the client address, literally
    widths = {len(row) for row in cells["rows"]}
    assert len(widths) <= 3  # Connections (7), Violations (6), Latency (6): no cell split by a '|'


def test_html_holds_every_value_as_data_shown_escaped(hostile):
    """The page carries its values as JSON inside one script element and its
    code puts them in as text (tests/test_report_browser.py sees them on the
    page): here, no value may end that element or reach the file raw."""
    page = run_cli("analyze", "--format", "html", hostile).stdout
    shows_no_raw_control(page)
    opened, closed = re.findall(r"<script[\s>]", page, re.I), re.findall(r"</script[\s>]", page, re.I)
    assert len(opened) == len(closed) == 3  # the data, uPlot, the page's own
    assert "-<b>.mcap" not in page and "alert(1)" in page
    data = page_data(page)
    assert shown(HOSTILE) in [c for r in data["sections"] if r["id"] == "connections"
                              for row in r["table"]["rows"] for c in row["c"]]  # the client address, as shown


def test_junit_parses_and_holds_the_values_escaped(hostile, tmp_path):
    result = run_cli("analyze", "--format", "junit", hostile)
    shows_no_raw_control(result.stdout)
    root = ET.fromstring(result.stdout)
    texts = [e.text or "" for e in root.iter()] + [v for e in root.iter() for v in e.attrib.values()]
    assert any("<script>alert(1)</script>]]>" in t and "\\x1b[31m" in t for t in texts)
    assert any("[bold]" in t for t in texts)


def test_replay_output_quotes_recorded_and_replayed_bytes_escaped(hostile):
    async def replay() -> tuple[int, str, str]:
        async with EchoServer() as echo:  # answers with what the client sends: hostile bytes both ways
            return await run_process_async("replay", str(hostile), "--target", f"{LOCAL}:{echo.port}", "--pace", "max",
                                  "--timeout", "0.5", "-v")
    code, out, err = asyncio.run(replay())
    assert code in (0, 1), err
    assert "\\x1b[31mRED" in out
    shows_no_raw_control(out + err)


@pytest.mark.slow
async def test_record_echo_lines_are_escaped(tmp_path):
    async with EchoServer() as server:
        rec = await RecordProcess.start(server.port, tmp_path / "r.mcap", "--analyze")
        reader, writer = await rec.connect()
        writer.write(HOSTILE_BYTES)
        await reader.readexactly(len(HOSTILE_BYTES))
        writer.close()
        code, out, err = await rec.finish()
    assert code == 0, err
    assert "\\x1b[31mRED" in out  # the violation line quotes the garbage, escaped
    shows_no_raw_control(out + err)


async def test_the_tui_shows_hostile_text_literally(hostile):
    app = WhiztapApp(FileSource(str(hostile)))
    async with app.run_test(size=SIZE) as pilot:
        await loaded(pilot)
        await settled(pilot)
        client = app.connections.get_cell("1", "client")
        assert client.plain.startswith("\\x1b[31mRED\\x1b]8;;http://evil\\x07")
        assert "[bold]B[/bold][link=http://e]L[/link]" in client.plain and not client.spans
        store = app.model.store
        garbage = next(n for n in range(store.count) if HOSTILE_BYTES[:8] in store.raw(n))
        console = Console(width=200, record=True, file=open(os.devnull, "w"))
        console.print(describe_frame(store, garbage))
        shown = console.export_text()
        assert "[bold]B[/bold][link=http://e]L[/link]" in shown and "<script>alert(1)</script>" in shown
        shows_no_raw_control(shown)
        await pilot.press("j")
        await until(pilot, lambda: app.detail.frame is not None, "the detail pane")
        shows_no_raw_control(app.export_screenshot())


class _Cells(html.parser.HTMLParser):
    """The text of every <td> and <code>, and the cells of each table row."""

    def __init__(self) -> None:
        super().__init__(convert_charrefs=True)
        self.cells: dict[str, list] = {"td": [], "code": [], "rows": []}
        self._open: list[str] = []

    def handle_starttag(self, tag: str, attrs: list) -> None:
        if tag == "tr":
            self.cells["rows"].append([])
        if tag in ("td", "code"):
            self._open.append(tag)
            self.cells[tag].append("")
            if tag == "td":
                self.cells["rows"][-1].append(tag)

    def handle_endtag(self, tag: str) -> None:
        if tag in ("td", "code") and self._open:
            self._open.pop()

    def handle_data(self, data: str) -> None:
        for tag in set(self._open):
            self.cells[tag][-1] += data


def _html_cells(page: str) -> dict[str, list]:
    parser = _Cells()
    parser.feed(page)
    return parser.cells


# -- the escaping helpers, on any text -------------------------------------------------------------

ANY_TEXT = st.text(st.characters(codec=None, exclude_categories=()), max_size=60) | st.text(
    st.sampled_from(list("\x1b\x00\x07\x85\x9b\u202e\n\r\t<>&|`*_[]\\#-+.!~ a1")), max_size=40)


@settings(max_examples=300, deadline=None)
@given(ANY_TEXT)
def test_printable_shows_every_character_and_is_stable(text):
    from whiztap.analyzer.protocol.text import printable

    shown_text = printable(text)
    assert shown_text.isprintable()
    element = ET.Element("v", a=shown_text)
    element.text = shown_text
    back = ET.fromstring(ET.tostring(element, encoding="unicode"))  # legal XML 1.0, read back whole
    assert back.text == shown_text or (not shown_text and back.text is None)
    assert printable(shown_text) == shown_text  # escaping what is shown changes nothing
    if text.isprintable():
        assert shown_text == text


@pytest.mark.slow
@settings(max_examples=300, deadline=None)
@given(ANY_TEXT, ANY_TEXT)
def test_a_markdown_cell_reads_as_the_value_and_never_as_html(value, frame):
    from whiztap.analyzer.analysis.report.text import md_code, md_text
    from whiztap.analyzer.protocol.text import printable

    table = f"| a | b |\n|---|---|\n| {md_text(value)} | {md_code(frame)} |\n"
    page = MarkdownIt("commonmark").enable("table").render(table)
    cells = _html_cells(page)
    assert len(cells["rows"][-1]) == 2  # no cell split or merged
    assert cells["td"][-2] == printable(value).strip()
    if frame:
        assert cells["code"][-1] == printable(frame)
    tags = re.findall(r"</?([a-z]+)", page)
    assert set(tags) <= {"table", "thead", "tbody", "tr", "th", "td", "code"}


def test_a_replay_that_reached_no_server_leaves_no_output(tmp_path):
    """An unreachable target left an empty recording at -o, and the retry was
    then refused because the output existed."""
    out = tmp_path / "replayed.mcap"
    for _ in range(2):  # the retry is not refused
        result = run_cli("replay", SAMPLE, "--target", f"{LOCAL}:{closed_port()}", "-o", out)
        assert result.returncode == 2 and "cannot connect" in result.stderr
        assert list(tmp_path.iterdir()) == []
