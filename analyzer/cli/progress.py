"""A progress bar over files' bytes for long reads, on a terminal only.

The files may be local or behind URLs (``whiztap.analyzer.recording.remote``):
sizes and opening go through ``part_size`` and ``open_part``."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from rich.console import Console

    from whiztap.analyzer.recording.remote import PartFile, RemotePart


class ByteProgress:
    """A progress bar over files' bytes, on a terminal, for files that take a
    moment: ``open`` counts what is read through it, ``update`` takes a
    position from a reader that does its own reading (pcap import)."""

    THRESHOLD = 16 * 1024 * 1024

    def __init__(self, paths: list, enabled: bool, doing: str = "analysing") -> None:
        from whiztap.analyzer.recording.remote import part_size

        total = sum(part_size(p) for p in paths)
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
        """A whole file was read elsewhere (a worker process, a cluster's worker)."""
        if self.bar is not None:
            from whiztap.analyzer.recording.remote import part_size

            self.bar.advance(self.task, part_size(path))

    def done_all(self, paths: Iterable) -> None:
        """``done`` for each of a recording's parts."""
        for path in paths:
            self.done(path)

    def update(self, position: int) -> None:
        """Bytes done so far, in all: for readers that do their own reading."""
        if self.bar is not None:
            self.bar.update(self.task, completed=position)

    def open(self, path: Path | RemotePart) -> PartFile:
        """``path`` opened through the bar: what is read moves it, and the rest
        of the file when it is closed (readers stop before the index at its end)."""
        from whiztap.analyzer.recording.remote import open_part, part_size

        f = open_part(path)
        if self.bar is None:
            return f
        bar, task, size = self.bar, self.task, part_size(path)

        class Counting:
            read_so_far = 0

            def read(self, n: int = -1) -> bytes:
                data = f.read(n)
                self.read_so_far += len(data)
                bar.advance(task, len(data))
                return data

            def close(self) -> None:
                bar.advance(task, max(0, size - self.read_so_far))
                self.read_so_far = size
                f.close()

            def __enter__(self) -> Counting:  # readers close it with ``with``
                return self

            def __exit__(self, *exc: object) -> None:
                self.close()

        return Counting()


def _stderr_console() -> Console:
    from rich.console import Console

    return Console(stderr=True)
