"""A file of named faults: ``--faults FILE`` of ``record``, ``tui`` and ``demo``.

It is TOML, one table under ``faults`` per fault, named by its key, with the
SPEC (``spec.py``) as ``spec`` and no other key::

    [faults.slow-server]
    spec = "delay:200ms dir:s2c"

    [faults.flaky-answers]
    spec = "drop dir:s2c kind:response every:2"

Whatever the file holds, reading it ends in its faults or in one FaultSpecError
line naming the file (and the fault): a file nested thousands deep (which
Python's TOML reader meets with a RecursionError) or with more faults than may
be in force at once (``MAX_FAULTS``) included.
"""

from __future__ import annotations

import tomllib
from pathlib import Path
from typing import Any

from whiztap.analyzer.mitm.faults import MAX_FAULTS
from whiztap.analyzer.mitm.spec import FaultSpec, FaultSpecError, parse_fault
from whiztap.analyzer.protocol.text import printable


def _read_toml(path: Path) -> dict[str, Any]:
    where = printable(str(path))
    try:
        with path.open("rb") as f:
            return tomllib.load(f)
    except FileNotFoundError:
        raise FaultSpecError(f"{where}: no such file") from None
    except OSError as e:
        raise FaultSpecError(f"{where}: cannot read it: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise FaultSpecError(f"{where}: not TOML: not UTF-8 text") from None
    except tomllib.TOMLDecodeError as e:
        raise FaultSpecError(f"{where}: not TOML: {e}") from None
    except RecursionError:  # arrays or inline tables nested thousands deep: no fault file is
        raise FaultSpecError(f"{where}: not a fault file: its values are nested too deeply to read") from None


def load_faults(path: str | Path) -> list[FaultSpec]:
    """The named faults of a TOML file (the format is this module's docstring),
    in the file's order; FaultSpecError naming the file (and the fault)."""
    path = Path(path)
    where = printable(str(path))
    document = _read_toml(path)
    faults = document.get("faults")
    extra = sorted(set(document) - {"faults"})
    if extra:
        raise FaultSpecError(f"{where}: unknown key {printable(extra[0])!r}: faults go in [faults.NAME] tables")
    if not isinstance(faults, dict) or not faults:
        raise FaultSpecError(f'{where}: no faults: expected tables such as [faults.slow-server] with spec = "..."')
    if len(faults) > MAX_FAULTS:
        raise FaultSpecError(f"{where}: {len(faults):,} faults; at most {MAX_FAULTS} may be in force at once")
    specs = []
    for name, table in faults.items():
        fault = f"{where}: fault {printable(name)!r}"
        if not isinstance(table, dict):
            raise FaultSpecError(f'{fault} is not a table with spec = "..."')
        if "spec" not in table:
            raise FaultSpecError(f"{fault} has no spec")
        if not isinstance(table["spec"], str):
            raise FaultSpecError(f"{fault}: spec is not a string")
        unknown = sorted(set(table) - {"spec"})
        if unknown:
            raise FaultSpecError(f"{fault}: unknown key {printable(unknown[0])!r} (a fault has only spec)")
        try:
            specs.append(parse_fault(table["spec"], name))
        except FaultSpecError as e:
            raise FaultSpecError(f"{fault}: {e}") from None
    return specs
