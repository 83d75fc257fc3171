"""One base class for whiztap's own errors, and the one line the command line
makes of it.

Every exception class the packages define is a ``WhiztapError`` (but the few
that only signal between parts of whiztap, listed here with why), found by
importing every module, so a new error class that forgets its base fails
here.  The root of the command line turns a ``WhiztapError`` that no command
caught into its message on one line and exit status 2: never a traceback,
never "unexpected error".
"""

from __future__ import annotations

import importlib
import inspect
import pkgutil
from importlib.metadata import EntryPoint

import click
import pytest

from whiztap.analyzer.cli import root
from whiztap.analyzer.errors import WhiztapError
from whiztap.analyzer.recording.recover import RecoverError
from tests.cli_support import run_cli

PACKAGES = ("whiztap.analyzer", "whiztap.sniffer", "whiztap.tui")

# Exceptions that carry no message for a user: one part of whiztap tells another
# that something happened, and that part acts on it.
SIGNALS = {
    "whiztap.analyzer.analysis.instep.OutOfStep": "a delivery that is not the next read: the sides re-sync",
    "whiztap.analyzer.analysis.merge.DuplicateResult": "a retried task's result came twice: a bug if raised",
    "whiztap.analyzer.recording.sets.Stopped": "a follower was told to stop",
    "whiztap.sniffer.replay.pacing.Stopped": "a replay was stopped while waiting for its turn",
}


def _exception_classes() -> dict[str, type[BaseException]]:
    """Every exception class defined in the packages, by its qualified name."""
    found: dict[str, type[BaseException]] = {}
    for package in PACKAGES:
        module = importlib.import_module(package)
        names = [package] + [m.name for m in pkgutil.walk_packages(module.__path__, package + ".")]
        for name in names:
            for _, cls in inspect.getmembers(importlib.import_module(name), inspect.isclass):
                if issubclass(cls, BaseException) and cls.__module__ == name:
                    found[f"{name}.{cls.__qualname__}"] = cls
    return found


def test_every_error_class_of_the_packages_is_a_whiztap_error() -> None:
    classes = _exception_classes()
    assert len(classes) > 40  # the walk found the packages' modules
    assert set(SIGNALS) <= set(classes), "a signal listed here is gone: take it off the list"
    not_errors = sorted(name for name, cls in classes.items()
                        if not issubclass(cls, WhiztapError) and name not in SIGNALS)
    assert not_errors == [], "derive these from whiztap.analyzer.errors.WhiztapError (or list a signal)"
    assert not [name for name in SIGNALS if issubclass(classes[name], WhiztapError)]


def _raise_it() -> None:
    """A command whose library error no handler of its own catches."""
    raise RecoverError("half.mcap: no footer; try 'whiztap recover'")


UNCAUGHT = click.Command("uncaught", callback=_raise_it)


@pytest.fixture
def uncaught_command(monkeypatch: pytest.MonkeyPatch) -> str:
    """``UNCAUGHT`` among the commands the root loads, as a package adds one."""
    monkeypatch.setitem(root.cli._entry_points, "uncaught",
                        EntryPoint("uncaught", f"{__name__}:UNCAUGHT", "whiztap.commands"))
    return "uncaught"


def test_the_root_turns_an_uncaught_whiztap_error_into_one_line(uncaught_command: str) -> None:
    result = run_cli(uncaught_command)
    assert result.returncode == 2
    assert result.stderr == "whiztap: half.mcap: no footer; try 'whiztap recover'\n"
    assert result.stdout == ""


def test_a_command_failure_is_a_whiztap_error_too() -> None:
    from whiztap.analyzer.cli.errors import CommandFailed

    assert issubclass(CommandFailed, WhiztapError)
    result = run_cli("cat", "no-such-recording.mcap")
    assert result.returncode == 2
    assert result.stderr.startswith("whiztap: ") and result.stderr.count("\n") == 1, result.stderr
