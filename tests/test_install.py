"""whiztap installed from its wheel lives under one name, ``whiztap``.

Installed, ``analyzer``, ``sniffer`` and ``tui`` would be top-level names that
other projects use too (PyPI has a ``sniffer``; many projects have a ``tui``),
and whiztap's pytest plugin is loaded in other projects' test runs.  So this
test builds the wheel, installs it into a fresh venv beside top-level packages
``analyzer``, ``sniffer`` and ``tui`` of another project's own, and runs a small
project's tests there through the plugin: the simulator as the live server,
a recording made through the proxy, then served by the stub and replayed.

The fresh venv has no pip and installs no dependencies (that would take
minutes): a ``.pth`` file points it at a folder of links to the test venv's
third-party packages, whiztap's own excepted, so the only whiztap it can
import is the wheel's.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest


ROOT = Path(__file__).resolve().parent.parent
PACKAGES = ("analyzer", "sniffer", "tui")

PROJECT_TEST = '''
import asyncio
from pathlib import Path

import pytest

import analyzer
import sniffer
import tui
from whiztap.sniffer.pytest_plugin import BackgroundLoop
from whiztap.sniffer.sim.client import Client
from whiztap.sniffer.sim.simulator import Simulator

PASSWORD = "progwhiz"


@pytest.fixture
def whiztap_target():
    with BackgroundLoop() as background:
        sim = Simulator(password=PASSWORD, seed=1)
        background.run(sim.start())
        yield f"127.0.0.1:{sim.port}"
        background.run(sim.close())


async def configuration_size(address):
    host, port = address.rsplit(":", 1)
    async with await Client.connect(host, int(port), password=PASSWORD) as client:
        return len((await client.fetch_configuration()).channels)


def test_our_own_top_level_packages_are_not_shadowed():
    assert (analyzer.MARK, sniffer.MARK, tui.MARK) == ("analyzer", "sniffer", "tui")


def test_whiztap_is_the_installed_wheel():
    import whiztap.tui
    import whiztap.sniffer.pytest_plugin as plugin

    site = Path(__file__).parent.parent / "venv"
    assert site in Path(whiztap.tui.__file__).parents
    assert site in Path(plugin.__file__).parents


@pytest.mark.whiztap("recordings/configuration.mcap", password=PASSWORD)
def test_the_client_reads_the_configuration(whiztap_server):
    assert asyncio.run(configuration_size(whiztap_server.address)) > 0


@pytest.mark.whiztap("recordings/configuration.mcap", password=PASSWORD)
def test_the_simulator_still_answers_as_recorded(whiztap_replay):
    assert whiztap_replay(pace="max").counts["match"] > 0
'''


def _run(args: list[str | Path], cwd: Path, env: dict[str, str]) -> str:
    done = subprocess.run([str(a) for a in args], cwd=cwd, env=env, capture_output=True, text=True, timeout=120)
    output = done.stdout + done.stderr
    assert done.returncode == 0, f"{' '.join(map(str, args))} exited {done.returncode}:\n{output}"
    return output


def _wheel(tmp: Path, env: dict[str, str]) -> Path:
    """Build from a copy of the sources, so the build leaves nothing in the work tree."""
    source = tmp / "source"
    source.mkdir()
    for name in ("pyproject.toml", "README.md"):
        shutil.copy2(ROOT / name, source / name)
    for package in PACKAGES:
        shutil.copytree(ROOT / package, source / package, ignore=shutil.ignore_patterns("__pycache__"))
    _run([sys.executable, "-m", "pip", "wheel", "--quiet", "--no-deps", "-w", tmp / "dist", source], tmp, env)
    (wheel,) = (tmp / "dist").glob("whiztap-*.whl")
    return wheel


def _fresh_venv(tmp: Path, env: dict[str, str]) -> Path:
    """A venv without pip that sees this venv's third-party packages, not its whiztap."""
    venv = tmp / "venv"
    _run([sys.executable, "-m", "venv", "--without-pip", venv], tmp, env)
    site = Path(sysconfig.get_paths()["purelib"])
    deps = tmp / "deps"
    deps.mkdir()
    for entry in site.iterdir():
        if not entry.name.startswith(("whiztap", "__editable__", "_whiztap")) and entry.suffix != ".pth":
            (deps / entry.name).symlink_to(entry)
    (new_site,) = (venv / "lib").glob("python3*/site-packages")
    (new_site / "deps.pth").write_text(f"{deps}\n")
    return venv


def _foreign_packages(tmp: Path) -> Path:
    """Another project's own top-level analyzer, sniffer and tui."""
    foreign = tmp / "foreign"
    for package in PACKAGES:
        (foreign / package).mkdir(parents=True)
        (foreign / package / "__init__.py").write_text(f"MARK = {package!r}\n")
    return foreign


@pytest.mark.slow
def test_the_wheel_installs_under_one_name_and_its_plugin_runs_beside_other_top_level_packages(
        tmp_path: Path) -> None:
    env = {k: v for k, v in os.environ.items() if not k.startswith(("PYTHON", "PYTEST", "VIRTUAL_ENV"))}
    wheel = _wheel(tmp_path, env)
    tops = {name.split("/")[0] for name in zipfile.ZipFile(wheel).namelist()}
    assert {top for top in tops if not top.endswith(".dist-info")} == {"whiztap"}, tops
    venv = _fresh_venv(tmp_path, env)
    _run([sys.executable, "-m", "pip", "--python", venv / "bin" / "python", "install", "--quiet", "--no-deps",
          "--no-index", wheel], tmp_path, env)

    env["PYTHONPATH"] = str(_foreign_packages(tmp_path))
    env["PYTHONDONTWRITEBYTECODE"] = "1"  # the linked packages' caches are this venv's: leave them alone
    project = tmp_path / "project"
    project.mkdir()
    (project / "test_client.py").write_text(textwrap.dedent(PROJECT_TEST))
    python = venv / "bin" / "python"
    pytest_args = [python, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                   "-W", "error::pytest.PytestUnknownMarkWarning"]

    recorded = _run([*pytest_args, "--whiztap-record=once"], project, env)
    assert "4 passed" in recorded, recorded
    assert (project / "recordings" / "configuration.mcap").is_file()
    served = _run(pytest_args, project, env)  # record mode none: the stub serves the recording
    assert "4 passed" in served, served

    help_text = _run([venv / "bin" / "whiztap", "--help"], project, env)
    for command in ("record", "analyze", "replay", "tui"):
        assert command in help_text
