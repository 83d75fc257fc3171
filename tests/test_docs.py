"""The docs say what is true: the protocol page lists every rule and checksum
candidate that exists, and the README's session runs as written."""

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from whiztap.analyzer.protocol.checksum import CHECKSUM_RULES
from whiztap.analyzer.protocol.rules import RULES

PROTOCOL = (Path(__file__).parent.parent / "docs" / "protocol.md").read_text()


def test_every_rule_is_documented_with_its_severity():
    for rule in RULES.values():
        assert f"| `{rule.id}` | {rule.severity} |" in PROTOCOL, rule.id


def test_every_checksum_rule_is_documented():
    for name in CHECKSUM_RULES:
        assert f"`{name}`" in PROTOCOL, name


# -- the README's session, run as written --------------------------------------------------------

README = (Path(__file__).parent.parent / "README.md").read_text()


def _readme_session() -> list[str]:
    block = README.split("## A session, end to end", 1)[1].split("```", 2)[1]
    return [line.split("#", 1)[0].strip() for line in block.strip().splitlines() if line.strip()]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_the_readme_session_runs_as_written(tmp_path):
    """Each line of the README's session, in order, in a shell.  What a person
    does between lines is done here too: wait until a server started with '&'
    accepts connections, and until a killed recorder has exited."""
    lines = _readme_session()
    assert lines[0].startswith("whiztap sim --port 5000 &") and lines[-1].startswith("whiztap cat")
    ports = {"5000": str(free_port()), "6000": str(free_port())}
    script = ["set -u"]
    jobs = 0
    for line in lines:
        for old, new in ports.items():
            line = line.replace(old, new)
        if line.startswith("kill %"):
            script += [line, f"wait {line.split()[1]}"]
            continue
        script.append(line)
        if line.endswith("&"):
            jobs += 1
            port = ports["5000"] if jobs == 1 else ports["6000"]
            script.append(f"until (exec 3<>/dev/tcp/127.0.0.1/{port}) 2>/dev/null; do sleep 0.05; done")
        else:
            script.append('echo "exit $?"')
    script += ["kill %1", "wait %1"]
    env = dict(os.environ, PATH=f"{Path(sys.executable).parent}{os.pathsep}{os.environ['PATH']}")
    result = subprocess.run(["bash", "-c", "\n".join(script)], cwd=tmp_path, env=env, capture_output=True,
                            text=True, timeout=120, stdin=subprocess.DEVNULL)
    out = result.stdout
    assert "Configuration Settings: 24 channels" in out and "sensor 12 = " in out, (out, result.stderr)
    statuses = [line for line in out.splitlines() if line.startswith("exit ")]
    # the two clients, analyze (0, or 1 when a rule is broken) and cat
    assert len(statuses) == 4, (out, result.stderr)
    assert statuses[:2] == ["exit 0", "exit 0"] and statuses[2] in ("exit 0", "exit 1") and statuses[3] == "exit 0", (
        out, result.stderr)
    assert (tmp_path / "session.mcap").exists() and "whiztap conformance report" in out
    assert "Traceback" not in result.stderr
