"""Every output a person can see, in one registry, and the password looked for in each.

The secret tests (test_secrets.py: the recorder; test_middle_outputs.py: the
proxy in the middle) read what they check from here, and
``test_middle_outputs.py::test_every_output_is_registered`` holds the
registry to the code's own lists, so an output added without a reader here
fails a test rather than going unchecked:

- ``FILE_OUTPUTS``: what reads a recording (every topic's messages, ``cat``,
  ``analyze``, ``info``, ``export --pcap``, ``replay --dry-run``, the TUI);
  every ``--format`` choice of ``cat``, ``analyze`` and ``info``, every topic
  the format defines, and every ``whiztap`` command is either here or in
  ``NOT_OUTPUTS`` with the reason;
- ``API_OUTPUTS``: every route of the control API (``http_api.ROUTES``) and
  how ``whiztap ctl`` shows its answer (every ``ctl`` subcommand);
- ``FLOW_VIEW``: every public attribute of a script's ``Flow``, which the
  logging script (``LOGGING_SCRIPT``) prints for each frame it sees;
- ``LIVE_OUTPUTS``: what shows the traffic while it flows (the live TUI,
  Foxglove live, the recorder's terminal, scripts' log lines), read by the
  end-to-end tests.

A leak is any ``WINDOW`` bytes of the password in a row, as text, in hex, or
as the base64 characters they fix at any alignment (reads and frames carry
their bytes in base64).
"""

from __future__ import annotations

import base64
import json
import threading
from collections.abc import Callable
from pathlib import Path

from whiztap.analyzer.analysis.report.formats import FORMATS
from whiztap.analyzer.recording.format import MIRROR_TOPICS, MITM_TOPICS, TOPICS
from whiztap.analyzer.protocol.text import plural
from whiztap.analyzer.recording.sets import find_one
from whiztap.sniffer.mitm import http_api
from whiztap.sniffer.mitm.scripts import Flow

from tests.cli_support import run_cli
from tests.record_support import read_all

SECRET = b"Kx9hunter2Tq4"
WINDOW = 8  # any 8 bytes of the password in a row count as a leak


def leak_forms(secret: bytes = SECRET, window: int = WINDOW) -> set[str]:
    """Every way a run of ``window`` bytes of the secret can show in text: as
    itself, and as the base64 characters it fixes at each of the 3 alignments."""
    forms: set[str] = set()
    for i in range(len(secret) - window + 1):
        piece = secret[i:i + window]
        forms.add(piece.decode("latin-1"))
        forms.update((piece.hex(), piece.hex(" ")))  # the HTML frame view shows bytes in hex too
        for pad in range(3):
            encoded = base64.b64encode(b"\0" * pad + piece).decode()
            first, last = -(-8 * pad // 6), 8 * (pad + window) // 6  # characters made of the piece's bits only
            forms.add(encoded[first:last])
    return forms


FORMS = leak_forms()


def leaks(text: str | bytes, forms: set[str] = FORMS) -> list[str]:
    if isinstance(text, bytes):
        text = text.decode("latin-1")
    return [form for form in forms if form in text]


def assert_no_leak(where: str, text: str | bytes, forms: set[str] = FORMS) -> None:
    found = leaks(text, forms)
    assert not found, f"the password shows in {where}: {found}"


# -- a recording's readers --------------------------------------------------------------------------


def run(*args: str, env: dict[str, str] | None = None) -> str:
    """A whiztap command in this process: it may fail a gate (1), never crash;
    all it printed, on stdout and stderr."""
    done = run_cli(*args, env=env)
    assert done.returncode in (0, 1), done.stderr
    return done.stdout + done.stderr


def topics_text(path: Path) -> str:
    """Every message of every topic as JSON, and the bytes of each base64 field decoded."""
    text = []
    for topic, messages in read_all(str(path)).items():
        for m in messages:
            text.append(f"{topic} {json.dumps(m)}")
            for key in ("data", "raw"):
                if isinstance(m.get(key), str):  # base64 bytes (a servo's "data" is its position, a number)
                    text.append(base64.b64decode(m[key]).decode("latin-1"))
    return "\n".join(text)


def tui_store_text(path: Path) -> bytes:
    """What the TUI holds for a recording: every frame's bytes, meaning and fields."""
    from whiztap.tui.data.model import TrafficModel
    from whiztap.tui.data.sources import FileSource

    model = TrafficModel(str(path))
    FileSource(find_one([str(path)])).feed(model, threading.Event())
    return store_text(model)


def store_text(model) -> bytes:
    """The TUI's frame store as text: the bytes of every row, what it means, and the proxy's marks."""
    store = model.store
    described = [repr(store.observation(i)) for i in range(store.count)] if hasattr(store, "observation") else []
    marks = [repr(m) for ms in getattr(store, "marks", {}).values() for m in ms]
    return bytes(store.raws) + "\n".join(described + marks).encode()


def export_pcap(path: Path) -> bytes:
    out = path.with_name(path.name + ".pcapng")
    run("export", str(path), "--pcap", str(out), "--force")
    return out.read_bytes()


def replay_dry_run(path: Path) -> str:
    return run("replay", str(path), "--dry-run")


def _analyze(fmt: str) -> Callable[[Path], str]:
    return lambda path: run("analyze", str(path), "--format", fmt, "--severity-threshold", "info")


def diff_every_format(path: Path) -> str:
    """``diff`` in each of its formats, the recording as B against a sample of
    other traffic, so each of its requests and answers shows as a difference."""
    sample = Path(__file__).resolve().parent.parent / "samples" / "clean-winsock.mcap"
    return "\n".join(run("diff", str(sample), str(path), "--format", fmt)
                     for fmt in ("text", "json", "markdown", "html"))


def _format(command: str, fmt: str, *more: str) -> Callable[[Path], str]:
    return lambda path: run(command, str(path), "--format", fmt, *more)


# name -> reader; ``(command, option, value)`` keys of FORMAT_CHOICES say which choice each covers
FILE_OUTPUTS: dict[str, Callable[[Path], str | bytes]] = {
    "every topic": topics_text,
    **{f"analyze --format {fmt}": _analyze(fmt) for fmt in FORMATS},
    "cat --format text": _format("cat", "text"),
    "cat --format jsonl": _format("cat", "jsonl"),
    "cat --interventions only": _format("cat", "text", "--interventions", "only"),
    "info --format text": _format("info", "text"),
    "info --format json": _format("info", "json"),
    "export --pcap": export_pcap,
    "replay --dry-run": replay_dry_run,
    "diff (every format)": diff_every_format,
    "the TUI (a recording)": tui_store_text,
}
# The cheap ones, for a property's every example.
QUICK_FILE_OUTPUTS = ("every topic", "cat --format text", "cat --format jsonl")
# Topics whose messages carry the traffic's bytes or meaning: the format's own lists.
TRAFFIC_TOPICS = tuple(t for t in (*TOPICS, *MITM_TOPICS, *MIRROR_TOPICS) if t != "/camera")
# ... of which only a recording made with --mirror has these: tests/test_mirror.py and
# tests/test_mirror_pairing.py reach and read them (the middle's cases cannot)
MIRROR_ONLY = tuple(MIRROR_TOPICS)

# Commands of the ``whiztap.commands`` entry points that show no recorded or proxied bytes, or
# whose output is read elsewhere, and why.
NOT_OUTPUTS = {
    "rules": "the rule table: no traffic",
    "decode": "decodes what the user types",
    "record": "its terminal, file and Foxglove are LIVE_OUTPUTS; its file is read by FILE_OUTPUTS; --ring's "
              "incident files are the recorder's own masked messages, read by FILE_OUTPUTS' readers in "
              "tests/test_ring.py::test_an_incident_by_rule_holds_the_window_around_it_and_the_opening_before_it",
    "recover": "writes a recording, which FILE_OUTPUTS read",
    "capture": "writes a recording, which FILE_OUTPUTS read",
    "wireshark-dissector": "a Lua file: no traffic",
    "ctl": "API_OUTPUTS: every subcommand",
    "sim": "the simulator: it is the server, and knows its own password",
    "client": "the client: it types the password",
    "stub": "serves a recording's server side; its miss lines and JSON show the requests a client asked "
            "after its password, never the password: "
            "tests/test_stub.py::test_no_miss_line_or_summary_shows_a_client_password; with --upstream "
            "it appends the new episodes to the recording (the password masked, every topic, cat and analyze "
            "of it read) and says how many it forwarded: "
            "tests/test_stub_episodes.py::test_a_missing_exchange_is_appended_and_then_served_without_the_server, "
            "tests/test_stub_episodes.py::test_the_command_appends_on_sigint_and_a_failed_or_killed_one_changes_nothing",
    "tui": "LIVE_OUTPUTS (live) and FILE_OUTPUTS (a recording)",
    "demo": "the simulator's own demo password through the TUI (LIVE_OUTPUTS)",
    "probe": "every report format, its progress lines and its --record recording are read by "
             "tests/test_probe_server.py::test_no_output_shows_the_password (probe server) and "
             "tests/test_probe_client.py::test_the_password_never_shows_in_the_report_even_when_the_client_prints_it",
    "fuzz": "its finding files (finding-N.mcap, test_finding_N.py), report and lines are read for the password "
            "by tests/test_fuzz.py (each finding written; --run's stdout and stderr)",
    "cut": "writes a recording of the input's messages byte for byte (masked stays masked: "
           "tests/test_cut.py::test_every_message_of_the_cut_is_a_message_of_the_original), which FILE_OUTPUTS "
           "read; its own line names only connection numbers and counts",
}
FILE_COMMANDS = {"analyze", "cat", "info", "export", "replay", "diff"}


# -- the control API and ``whiztap ctl`` ------------------------------------------------------------


def _ctl():
    import whiztap.sniffer.cli.ctl as ctl

    return ctl


def _lines(answer: object, show: Callable[[dict], list[str]]) -> str:
    """An answer as ``whiztap ctl`` shows it: text lines, and JSON (``--format json``)."""
    if not isinstance(answer, dict) or "error" in answer:
        return json.dumps(answer)
    return "\n".join(show(answer)) + "\n" + json.dumps(answer, indent=2)


def _held(a: dict) -> list[str]:
    return [_ctl().held_line(h) for h in a["held"]]


def _state(a: dict) -> list[str]:
    return _ctl().state_lines(a)


def _connections(a: dict) -> list[str]:
    return [_ctl().connection_line(c) for c in a["connections"]]


def _faults(a: dict) -> list[str]:
    return [_ctl().fault_line(f) for f in a["faults"]]


def _fault(a: dict) -> list[str]:
    return [_ctl().fault_line(a)]


def _held_one(verb: str) -> Callable[[dict], list[str]]:
    return lambda a: [f"{verb} #{a['id']} {a['text']}", _ctl().held_line(a)]


# (method, route pattern) -> (the ctl subcommands that show its answer, how)
API_OUTPUTS: dict[tuple[str, str], tuple[tuple[str, ...], Callable[[dict], list[str]]]] = {
    ("GET", "/state"): (("state",), _state),
    ("GET", "/connections"): (("connections",), _connections),
    ("GET", "/faults"): (("fault list",), _faults),
    ("POST", "/faults"): (("fault add",), _fault),
    ("DELETE", "/faults/{key}"): (("fault rm",), _fault),
    ("POST", "/faults/{key}/enable"): (("fault on", "fault off"), _fault),
    ("GET", "/intercept"): (("intercept",), lambda a: [f"intercept: {a['filter']}"]),
    ("PUT", "/intercept"): (("intercept",), lambda a: [f"intercept: {a['filter']}"]),
    ("GET", "/held"): (("held",), _held),
    ("POST", "/held/release-all"): (("release-all",), lambda a: [f"released {plural(a['released'], 'held frame')}"]),
    ("POST", "/held/{id}/release"): (("release",), _held_one("released")),
    ("POST", "/held/{id}/drop"): (("drop",), _held_one("dropped")),
    ("POST", "/inject"): (("inject",), lambda a: [f"injected {a['frame']} on #{a['conn']} {a['dir']}"]),
}


def route_key(method: str, path: str) -> tuple[str, str]:
    """The API_OUTPUTS key of a request: its route's pattern written as in http_api's table."""
    for want, pattern, _ in http_api.ROUTES:
        if want == method and pattern.match(path):
            return method, route_text(pattern.pattern)
    raise KeyError(f"{method} {path}: no route")


def route_text(pattern: str) -> str:
    """``^/held/([^/]+)/release$`` -> ``/held/{id}/release`` (``{key}`` under /faults)."""
    text = pattern.strip("^$")
    name = "{key}" if text.startswith("/faults") else "{id}"
    return text.replace("([^/]+)", name)


def api_text(method: str, path: str, answer: object) -> str:
    """What a person sees of one answer: its JSON, and ctl's lines for it."""
    _, show = API_OUTPUTS[route_key(method, path)]
    return _lines(answer, show)


# -- scripts --------------------------------------------------------------------------------------

# Every public attribute of a script's Flow that shows something (its methods act, they show nothing).
FLOW_VIEW = tuple(sorted(name for name, value in vars(Flow).items()
                         if not name.startswith("_") and isinstance(value, property)))
LOGGING_SCRIPT = f'''
"""Prints everything a script can see of each frame, as a user's logging script would."""
LOG = []
PRINT = True  # a test on the fake clock reads LOG instead
VIEW = {FLOW_VIEW!r}


def frame(flow):
    line = " ".join(f"{{name}}={{getattr(flow, name)!r}}" for name in VIEW)
    LOG.append(line)
    if PRINT:
        print(line, flush=True)
'''


def script_log(script) -> str:
    return "\n".join(script.module.LOG)


# -- what shows the traffic while it flows ------------------------------------------------------------

LIVE_OUTPUTS = (
    "the live TUI (frames, marks, held rows, the editor)",
    "Foxglove live (--foxglove)",
    "whiztap record's terminal (stdout and stderr)",
    "scripts' log lines",
    "the control API's answers and whiztap ctl",
)
