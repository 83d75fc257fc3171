"""A progress bar over files' bytes for long reads, on a terminal only."""

from __future__ import annotations

import sys
from pathlib import Path
from typing import IO


class ByteProgress:
    """A progress bar over files' bytes, on a terminal, for files that take a
    moment: ``open`` counts what is read through it, ``update`` takes a
    position from a reader that does its own reading (pcap import)."""

    THRESHOLD = 16 * 1024 * 1024

    def __init__(self, paths: list[Path], enabled: bool, doing: str = "analysing") -> None:
        total = sum(p.stat().st_size for p in paths)
        self.bar = None
        if enabled and total >= self.THRESHOLD and sys.stderr.isatty():
            from rich.progress import BarColumn, DownloadColumn, Progress, TimeRemainingColumn

            self.bar = Progress("[progress.description]{task.description}", BarColumn(), DownloadColumn(),
                                TimeRemainingColumn(), transient=True, console=_stderr_console())
            self.task = self.bar.add_task(doing, total=total)

    def __enter__(self) -> ByteProgress:
        if self.bar:
            self.bar.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self.bar:
            self.bar.stop()

    def done(self, path: Path) -> None:
        """A whole file was read elsewhere (a worker process)."""
        if self.bar is not None:
            self.bar.advance(self.task, path.stat().st_size)

    def update(self, position: int) -> None:
        """Bytes done so far, in all: for readers that do their own reading."""
        if self.bar is not None:
            self.bar.update(self.task, completed=position)

    def open(self, path: Path) -> IO[bytes]:
        f = open(path, "rb")  # noqa: SIM115 - closed by the caller
        if self.bar is None:
            return f
        bar, task = self.bar, self.task

        class Counting:
            def read(self, n: int = -1) -> bytes:
                data = f.read(n)
                bar.advance(task, len(data))
                return data

            def close(self) -> None:
                f.close()

        return Counting()  # type: ignore[return-value]


def _stderr_console():
    from rich.console import Console

    return Console(stderr=True)
