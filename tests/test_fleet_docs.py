"""docs/fleet.md's session runs as written: record with --meta, a fleet report,
the same on a LocalCluster (--dask local), and on a scheduler and workers
started by hand with the ``dask`` command, reading the recordings by URL."""

from __future__ import annotations

import json
import os
import re
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from tests.report_page import page_data

FLEET_DOC = (Path(__file__).parent.parent / "docs" / "fleet.md").read_text()
_PORT = re.compile(r"(?:--port |--listen 127\.0\.0\.1:|--dashboard-address 127\.0\.0\.1:|tcp://127\.0\.0\.1:)(\d+)")


def _session() -> list[str]:
    block = FLEET_DOC.split("## A fleet on one machine, end to end", 1)[1].split("```", 2)[1]
    return [line.strip() for line in block.strip().splitlines() if line.strip()]


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _script(lines: list[str]) -> str:
    """The lines in bash, each with what a person does between them: wait
    until a server started with '&' listens (a worker has nothing to wait
    for: analyze waits for it), and until a killed recorder has exited;
    every other line's exit status echoed."""
    ports = {p: str(_free_port()) for line in lines for p in _PORT.findall(line)}
    script = ["set -u"]
    for line in lines:
        line = re.sub(r"\b\d{4,5}\b", lambda m: ports.get(m.group(0), m.group(0)), line)
        script.append(line)
        if line.startswith("kill "):
            script.append("wait $! 2>/dev/null")
        elif line.endswith("&"):
            listened = re.search(r"(?:--port |--listen 127\.0\.0\.1:)(\d+)", line)
            if listened:
                script.append(f"until (exec 3<>/dev/tcp/127.0.0.1/{listened.group(1)}) 2>/dev/null; "
                              "do sleep 0.05; done")
        else:
            script.append('echo "exit $?"')
    # then the servers, the last started first (workers before their scheduler)
    # what Dask's processes log as they are stopped is not the session's
    return "\n".join(script + ["echo '--- stopping' >&2",
                                "for job in $(jobs -p | tac); do kill $job; wait $job 2>/dev/null; done"])


@pytest.mark.slow
def test_the_fleet_session_runs_as_written(tmp_path: Path) -> None:
    lines = _session()
    assert lines[0] == "mkdir fleet" and any("--dask local" in line for line in lines)
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    result = subprocess.run(["bash", "-c", _script(lines)], cwd=tmp_path, env=env, capture_output=True, text=True,
                            timeout=180, stdin=subprocess.DEVNULL)
    out, err = result.stdout, result.stderr.split("--- stopping")[0]
    statuses = [line for line in out.splitlines() if line.startswith("exit ")]
    # mkdir, two clients, then three analyze runs (r2's first command breaks a rule, a warning)
    assert statuses == ["exit 0"] * 6, (out, err)
    assert "Fleet by robot" in out and "Fleet by firmware" in out and "Traceback" not in err, err
    assert "Dask: 2 workers at tcp://127.0.0.1:" in err
    titles = [s["title"] for s in page_data((tmp_path / "fleet.html").read_text())["sections"]]
    assert "Fleet by robot / firmware" in titles
    report = json.loads((tmp_path / "fleet.json").read_text())
    assert [g["group"]["robot"] for g in report["fleet"][0]["groups"]] == ["r1", "r2"]
    assert all(f.startswith("file:///") for f in report["files"])
