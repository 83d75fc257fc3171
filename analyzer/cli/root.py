"""The ``whiztap`` command line: the root group and ``main()``.

Each package contributes subcommands through the ``whiztap.commands`` entry-point
group, loaded only when named, so this module imports nothing above the analyzer
and ``whiztap --help`` stays fast.  Command modules keep heavy imports (textual,
scapy, mcap) inside their functions.
"""

from __future__ import annotations

import functools
import os
import sys
from importlib.metadata import EntryPoint, entry_points

import click

from whiztap.analyzer import __version__
from whiztap.analyzer.cli.errors import EXIT_USAGE, warn
from whiztap.analyzer.errors import WhiztapError


class _LazyGroup(click.Group):
    @functools.cached_property
    def _entry_points(self) -> dict[str, EntryPoint]:
        # once: every scan reads every installed distribution's metadata, and
        # --help asks once per command
        return {ep.name: ep for ep in entry_points(group="whiztap.commands")}

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(self._entry_points)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        ep = self._entry_points.get(name)
        return ep.load() if ep is not None else None


@click.group(cls=_LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="whiztap")
def cli() -> None:
    """Record, replay and check Progwhiz Robotics Server API (Rev 1.8) traffic."""


_NO_ARGS_IS_HELP = getattr(click.exceptions, "NoArgsIsHelpError", ())  # click >= 8.2


def main() -> None:
    """The ``whiztap`` command: every error is one line on stderr, never a traceback."""
    try:
        cli.main(standalone_mode=False)
    except (click.exceptions.Abort, KeyboardInterrupt):
        click.echo("whiztap: interrupted", err=True)
        sys.exit(EXIT_USAGE)
    except _NO_ARGS_IS_HELP as e:  # a bare 'whiztap': the help, as click prints it
        e.show()
        sys.exit(e.exit_code)
    except click.UsageError as e:  # one line, like every other error, rather than click's three
        command = e.ctx.command_path if e.ctx is not None else "whiztap"
        warn(f"{e.format_message()} (see '{command} --help')")
        sys.exit(e.exit_code)
    except click.ClickException as e:
        e.show()
        sys.exit(e.exit_code)
    except click.exceptions.Exit as e:
        sys.exit(e.exit_code)
    except WhiztapError as e:  # the library's own, which no command put in its words: its line as it is
        warn(str(e))
        sys.exit(EXIT_USAGE)
    except Exception as e:  # the last line of defence: one line, not a traceback
        if os.environ.get("WHIZTAP_DEBUG"):
            raise
        warn(f"unexpected error: {type(e).__name__}: {e} (set WHIZTAP_DEBUG=1 to see where; please report it)")
        sys.exit(EXIT_USAGE)
