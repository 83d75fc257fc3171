"""whiztap fuzz server against the real simulator over real sockets: the clean
one gives nothing, each planted bug is found, shrunk and written as a
recording and a pytest that fails while the bug is there.

Runs are capped by executions (``--executions``), never by time, so they do
the same work on any machine."""

from __future__ import annotations

import asyncio
import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.outputs import assert_no_leak, leak_forms
from tests.report_page import page_data, sections, table_rows
from tests.cli_support import run_cli
from whiztap.sniffer.fuzz.findings import write
from whiztap.sniffer.fuzz.run import FuzzOptions, FuzzReport, Fuzzer
from whiztap.sniffer.fuzz.server import InProcess
from whiztap.sniffer.pytest_plugin import BackgroundLoop
from whiztap.sniffer.sim.bugs import BUGS as PLANTED
from whiztap.sniffer.sim.simulator import Simulator

PASSWORD = "fuzz-s3cret"
# (bug, seed, executions): a seed that finds the bug within the executions
# (a run is a function of its seed, so this holds on every machine), and the
# kind and rule it is found as.
BUGS = {
    "crash-on-frame": (1, 40, "crash", ""),
    "split-crash": (0, 20, "crash", ""),
    "out-of-range": (0, 20, "violation", "PW-RANGE-SENSOR"),
    "wrong-channel": (0, 20, "violation", "PW-PAIR-UNSOLICITED"),
}


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def fuzz(tmp_path: Path, bugs: tuple[str, ...], seed: int, executions: int, deadline: float = 1.0,
         mode: str = "winsock") -> FuzzReport:
    """A run in this process against the simulator (restarted after a crash), writing into ``tmp_path``."""
    port = free_port()
    address = ("127.0.0.1", port)
    tmp_path.mkdir(exist_ok=True)
    options = FuzzOptions(address, PASSWORD.encode(), seed, budget=300, executions=executions, deadline=deadline)

    async def start() -> Simulator:
        sim = Simulator(port=port, password=PASSWORD, bugs=bugs, mode=mode)
        await sim.start()
        return sim

    async def save(found, knowledge) -> None:
        await write(found, tmp_path, address, knowledge, options.password, options.deadline, seed)

    return asyncio.run(Fuzzer(options, InProcess(start), save).run())


@pytest.fixture
def simulator():
    """A simulator on a background loop, for a command run in this process: bugs -> HOST:PORT."""
    with BackgroundLoop() as background:
        sims = []

        def start(*bugs: str) -> str:
            sim = Simulator(password=PASSWORD, bugs=bugs)
            background.run(sim.start())
            sims.append(sim)
            return f"127.0.0.1:{sim.port}"

        yield start
        for sim in sims:
            background.run(sim.close())


@pytest.mark.slow
def test_the_clean_simulator_gives_no_finding(simulator, tmp_path):
    target = simulator()
    ran = run_cli("fuzz", "server", target, "--budget", 300, "--executions", 120, "--seed", 1,
                  "-o", tmp_path / "out", "--format", "json", env={"WHIZTAP_PASSWORD": PASSWORD})
    assert ran.returncode == 0, ran.stderr
    report = json.loads(ran.stdout)
    assert report["findings"] == [] and report["executions"] == 120
    assert list((tmp_path / "out").iterdir()) == []


# Every planted bug of the simulator's registry: (seed, executions, kind, rule)
# such that the run finds it (deadline 0.2 s, so hangs are quick to see and to
# shrink), and by which check: an analyzer rule, the fuzzer's own FUZZ-*
# rules, a hang or a crash.
EVERY_BUG = {
    **BUGS,
    "bad-config": (0, 2, "violation", "PW-CFG-DIGIT"),
    "out-of-order": (3, 3, "violation", "FUZZ-ANSWER-ORDER"),
    "drop-nth": (0, 4, "hang", ""),
    "any-password": (2, 2, "violation", "FUZZ-WRONG-PASSWORD-ACCEPTED"),
    "no-sendchkpass": (0, 2, "violation", "PW-HS-ORDER"),
    "bad-trailer": (3, 6, "hang", ""),
    "camera-length": (1, 3, "violation", "PW-FRAME-GARBAGE"),
    "silent-after-garbage": (0, 4, "hang", ""),
}


@pytest.mark.slow
@pytest.mark.parametrize("bug", BUGS)
def test_a_planted_bug_is_found_shrunk_and_written(bug, tmp_path):
    seed, executions, kind, rule = BUGS[bug]
    report = fuzz(tmp_path, (bug,), seed, executions)
    [found] = report.findings
    assert (found.verdict.kind, found.verdict.rule) == (kind, rule)
    assert found.shrunk and len(found.session) <= 2, [f.shown() for f in found.session]
    recording, test = tmp_path / "finding-1.mcap", tmp_path / "test_finding_1.py"
    assert found.recording == str(recording) and found.test == str(test)
    for path in (recording, test):
        assert PASSWORD.encode() not in path.read_bytes()
    analyzed = run_cli("analyze", recording, "--format", "json")
    assert analyzed.returncode in (0, 1), analyzed.stderr
    assert json.loads(analyzed.stdout)["connections"]


def test_every_planted_bug_has_a_case():
    assert set(EVERY_BUG) == set(PLANTED)


@pytest.mark.slow
@pytest.mark.parametrize("bug", PLANTED)
def test_every_planted_bug_is_found(bug, tmp_path):
    seed, executions, kind, rule = EVERY_BUG[bug]
    mode = PLANTED[bug].needs or "winsock"
    report = fuzz(tmp_path, (bug,), seed, executions, deadline=0.2, mode=mode)
    found = [f for f in report.findings if f.verdict.signature == (kind, rule)]
    assert found, [f.verdict for f in report.findings]
    assert found[0].shrunk, [f.shown() for f in found[0].session]
    for path in (found[0].recording, found[0].test):
        assert Path(path).is_file() and PASSWORD.encode() not in Path(path).read_bytes()


@pytest.mark.slow
def test_two_runs_with_one_seed_find_the_same(tmp_path):
    first = fuzz(tmp_path / "a", ("out-of-range", "drop-nth"), 5, 20, deadline=0.3)
    second = fuzz(tmp_path / "b", ("out-of-range", "drop-nth"), 5, 20, deadline=0.3)

    def shown(report: FuzzReport) -> list:
        return [(f.verdict.signature, f.execution, [x.shown() for x in f.session]) for f in report.findings]

    assert shown(first) == shown(second) and len(first.findings) >= 2


def _pytest(test: Path, target: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "WHIZTAP_PASSWORD": PASSWORD}
    return subprocess.run([sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider", str(test),
                           "--whiztap-target", target], capture_output=True, text=True, env=env,
                          cwd=test.parent, timeout=120)


@pytest.mark.slow
@pytest.mark.parametrize("bug", ["out-of-range", "crash-on-frame"])
def test_the_finding_test_fails_on_the_buggy_server_and_passes_on_the_clean_one(bug, tmp_path, simulator):
    seed, executions, _, _ = BUGS[bug]
    fuzz(tmp_path, (bug,), seed, executions)
    test = tmp_path / "test_finding_1.py"
    failing = _pytest(test, simulator(bug))
    assert failing.returncode == 1, failing.stdout + failing.stderr
    assert "1 failed" in failing.stdout
    passing = _pytest(test, simulator())
    assert passing.returncode == 0, passing.stdout + passing.stderr


@pytest.mark.slow
def test_replay_reads_a_finding_and_sees_the_crash(tmp_path, simulator):
    fuzz(tmp_path, ("split-crash",), 0, 20)
    ran = run_cli("replay", tmp_path / "finding-1.mcap", "--target", simulator("split-crash"),
                  "--segments", "exact", "--timeout", 1, env={"WHIZTAP_PASSWORD": PASSWORD})
    assert ran.returncode == 1, ran.stdout + ran.stderr


@pytest.mark.slow
def test_run_starts_the_server_and_restarts_it_after_a_crash(tmp_path):
    port = free_port()
    whiztap = Path(sys.executable).parent / "whiztap"
    command = f"{whiztap} sim --port {port} --password {PASSWORD} --bug crash-on-frame"
    ran = run_cli("fuzz", "server", f"127.0.0.1:{port}", "--budget", 300, "--executions", 40, "--seed", 1,
                  "-o", tmp_path, "--run", command, "--format", "json", env={"WHIZTAP_PASSWORD": PASSWORD})
    assert ran.returncode == 1, ran.stderr
    report = json.loads(ran.stdout)
    [found] = report["findings"]
    assert found["kind"] == "crash" and found["frames"] == 2 and found["shrunk"]
    assert PASSWORD not in ran.stdout + ran.stderr


def test_an_unreachable_target_is_one_line_and_status_2(tmp_path):
    ran = run_cli("fuzz", "server", f"127.0.0.1:{free_port()}", "--budget", 5, "-o", tmp_path)
    assert ran.returncode == 2
    assert ran.stderr.count("\n") == 1 and "cannot connect" in ran.stderr


def test_a_wrong_password_is_one_line_and_status_2(simulator, tmp_path):
    ran = run_cli("fuzz", "server", simulator(), "--budget", 5, "-o", tmp_path, "--password", "wrong")
    assert ran.returncode == 2 and ran.stderr.count("\n") == 1 and "password" in ran.stderr


def test_a_bad_output_folder_is_one_line_and_status_2(simulator, tmp_path):
    target = simulator()
    afile = tmp_path / "file"
    afile.write_text("")
    ran = run_cli("fuzz", "server", target, "--budget", 5, "-o", afile)
    assert ran.returncode == 2 and "not a folder" in ran.stderr and ran.stderr.count("\n") == 1
    (tmp_path / "old").mkdir()
    (tmp_path / "old" / "finding-1.mcap").write_bytes(b"")
    ran = run_cli("fuzz", "server", target, "--budget", 5, "-o", tmp_path / "old")
    assert ran.returncode == 2 and "--force" in ran.stderr


def test_the_html_page_lists_each_finding_with_its_minimal_session(simulator, tmp_path):
    seed, executions, kind, rule = EVERY_BUG["bad-config"]
    ran = run_cli("fuzz", "server", simulator("bad-config"), "--budget", 300, "--executions", executions,
                  "--seed", seed, "--deadline", 0.2, "-o", tmp_path / "out", "--format", "html",
                  env={"WHIZTAP_PASSWORD": PASSWORD})
    assert ran.returncode == 1, ran.stderr
    data = page_data(ran.stdout)
    assert data["verdict"] == {"passed": False, "text": "FAIL: 1 finding"}
    [finding] = table_rows(sections(data)["findings"])
    assert (finding["kind"], finding["rule"]) == (kind, rule)
    [linked] = sections(data)["findings"]["table"]["rows"]
    session = data["frames"][linked["f"]]["rows"]
    assert any(rule in frame["rules"] for frame in session)  # the frame that breaks it, decoded, one click away
    assert_no_leak("fuzz server --format html", ran.stdout + ran.stderr, leak_forms(PASSWORD.encode()))
