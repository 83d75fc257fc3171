"""Recordings named by URL (``s3://``, ``gs://``, ``file://``...), read through fsspec.

A fleet's recordings often live in object storage, and the machines of a Dask
cluster read them from there; copying each one to a local disk first would
double the I/O and need the disk.  fsspec turns a URL into a file object that
``RecordingScan`` reads in order (it needs ``read``, nothing else: it skips by
reading when the file is not a local one), so a URL is one more kind of part:
a ``RemotePart`` stands where a ``Path`` does, and ``open_part`` opens either.

fsspec is the ``fleet`` extra; ``s3://`` also needs s3fs (the ``s3`` extra),
``gs://`` gcsfs (``gcs``).  Credentials come from where those libraries look
(environment, config files, instance roles), on every machine that reads.

This is file reading, not socket I/O of the analyzer's own: fsspec is a file
abstraction, and what this module asks of it is what it asks of ``open()``
(a listing, a size, bytes in order).  Whatever connections s3fs or gcsfs make
underneath are that library's, as a network filesystem's are the kernel's;
the analyzer listens on nothing, connects to no peer and speaks no protocol.
"""

from __future__ import annotations

import errno
import posixpath
import re
from dataclasses import dataclass
from pathlib import Path
from types import TracebackType
from typing import IO, TYPE_CHECKING, Protocol

from whiztap.analyzer.errors import WhiztapError

if TYPE_CHECKING:
    from fsspec.spec import AbstractFileSystem

_URL = re.compile(r"^[A-Za-z][A-Za-z0-9+.-]*://")
_GLOB_CHARS = frozenset("*?[")
_PART_NAME = re.compile(r"^(?P<stem>.+)-\d{4,}\.mcap$")
HEAD_BLOCK = 64 * 1024  # what reading the metadata record fetches: it comes before the first chunk
SCAN_BLOCK = 8 * 1024 * 1024  # what a whole scan fetches per request: few round trips, bounded memory


class Readable(Protocol):
    """What a reader of a recording needs of its file: bytes in order, short
    only at its end (a local file, a URL's, one still being written)."""

    def read(self, n: int = -1, /) -> bytes: ...


class PartFile(Readable, Protocol):
    """A part of a recording opened for reading (``open_part``), closed with ``with``."""

    def close(self) -> None: ...

    def __enter__(self) -> PartFile: ...

    def __exit__(self, kind: type[BaseException] | None, error: BaseException | None,
                 trace: TracebackType | None, /) -> None: ...


class RemoteInputError(WhiztapError, ValueError):
    """A URL that names no readable recording, or a scheme nothing can read; one line."""


@dataclass(frozen=True)
class RemotePart:
    """One recording file behind a URL; ``size`` as listed (for the progress bar)."""

    url: str
    size: int = 0

    @property
    def name(self) -> str:
        return posixpath.basename(self.url.rstrip("/"))

    @property
    def parent(self) -> str:
        return self.url.rstrip("/").rpartition("/")[0]

    def __str__(self) -> str:
        return self.url


def is_url(name: str) -> bool:
    """Whether a name the user gave is a URL (``scheme://...``) rather than a local path."""
    return _URL.match(name) is not None


def part_size(part: Path | RemotePart) -> int:
    """A part's size in bytes: a URL's as listed, a file's as it is now."""
    return part.size if isinstance(part, RemotePart) else part.stat().st_size


def open_part(part: str | Path | RemotePart, head: bool = False) -> PartFile:
    """A part opened for reading in order; ``head``: only its first records are
    wanted (the metadata).  A URL's failures come as ``OSError`` with the
    library's words, as a local file's do."""
    if not isinstance(part, RemotePart):
        return open(part, "rb")  # closed by the caller
    try:
        import fsspec

        f = fsspec.open(part.url, "rb", block_size=HEAD_BLOCK if head else SCAN_BLOCK).open()
    except OSError as e:
        raise OSError(e.errno or errno.EIO, _reason(e)) from None
    except Exception as e:  # each backend has its own exceptions (auth, throttling, ...)
        raise OSError(errno.EIO, _reason(e)) from None
    return _RemoteFile(f)


class _RemoteFile:
    """A URL's file object whose read failures are ``OSError``: a network
    error in the middle of a file costs that file, in words, not the run."""

    def __init__(self, f: IO[bytes]) -> None:
        self._f = f

    def read(self, n: int = -1) -> bytes:
        try:
            return self._f.read(n)
        except Exception as e:  # as in open_part
            raise OSError(getattr(e, "errno", None) or errno.EIO, _reason(e)) from None

    def close(self) -> None:
        self._f.close()

    def __enter__(self) -> _RemoteFile:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _reason(e: BaseException) -> str:
    """An exception from a storage library as one line."""
    text = " ".join(str(e).split()) or type(e).__name__
    return text if isinstance(e, OSError) else f"{type(e).__name__}: {text}"


def remote_parts(url: str) -> list[RemotePart]:
    """The recording files a URL names: one file (with the other parts of a
    split recording beside it), every ``.mcap`` below a folder, or what a glob
    matches.  Raises RemoteInputError."""
    fs, path = _filesystem(url)
    try:
        if _GLOB_CHARS & set(path):
            found = fs.glob(path, detail=True)
            if not any(p.endswith(".mcap") for p in found):
                raise RemoteInputError(f"{url}: no recording matches this pattern")
        elif fs.isdir(path):
            found = fs.find(path, detail=True)
            if not any(p.endswith(".mcap") for p in found):
                raise RemoteInputError(f"{url}: no .mcap recordings in this folder")
        elif fs.exists(path):
            found = _with_siblings(fs, path)
        else:
            raise RemoteInputError(f"{url}: no such file")
    except RemoteInputError:
        raise
    except Exception as e:  # as in open_part: the backend's words, in one line
        raise RemoteInputError(f"{url}: cannot list ({_reason(e)})") from None
    return [RemotePart(fs.unstrip_protocol(p), int(info.get("size") or 0)) for p, info in sorted(found.items())
            if p.endswith(".mcap") and info.get("type", "file") == "file"]


def _with_siblings(fs: AbstractFileSystem, path: str) -> dict[str, dict]:
    """A file, and the numbered parts beside it when its name is one (the split
    recording it belongs to is grouped by metadata afterwards, as for files)."""
    m = _PART_NAME.match(posixpath.basename(path))
    if m is None:
        return {path: fs.info(path)}
    pattern = posixpath.join(posixpath.dirname(path), _glob_escape(m["stem"]) + "-[0-9][0-9][0-9][0-9]*.mcap")
    found = fs.glob(pattern, detail=True)
    return found or {path: fs.info(path)}


def _glob_escape(text: str) -> str:
    return re.sub(r"([*?\[])", r"[\1]", text)


def _filesystem(url: str) -> tuple[AbstractFileSystem, str]:
    """The fsspec filesystem for a URL, or why there is none."""
    try:
        import fsspec
    except ImportError:
        raise RemoteInputError(f"{url}: reading URLs needs fsspec: pip install 'whiztap[fleet]'") from None
    try:
        return fsspec.core.url_to_fs(url)
    except ImportError as e:  # a known scheme whose library is missing (s3fs, gcsfs)
        raise RemoteInputError(f"{url}: {_reason(e)} (docs/fleet.md says which extra installs it)") from None
    except Exception as e:  # an unknown scheme, a bad URL
        raise RemoteInputError(f"{url}: {_reason(e)}") from None
