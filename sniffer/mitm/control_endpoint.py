"""Where the control API listens, and how a client finds it (docs/faults.md,
"Reaching the control API").

Two transports.  A Unix domain socket (the default) is locked by the file
system: the socket is mode 0600 in a folder only its user can open, so no
other user and no web page can reach it, and it needs no token.  TCP can be
reached by every program on the host (a browser included) and, on another
address, by the network, so it takes a bearer token, and the server checks
each request's Host, Origin and Content-Type (``control_guard``).

The default socket lives in one folder per user, found again by ``whiztap
ctl`` without being told: ``$XDG_RUNTIME_DIR/whiztap`` (a folder the login
session owns, mode 0700 by the XDG spec), or ``<tmp>/whiztap-<uid>`` where
there is none, as tmux does.  A folder there that another user owns, or that
others may open, is refused rather than used: someone else could otherwise
put a socket of theirs where ``ctl`` looks.
"""

from __future__ import annotations

import contextlib
import errno
import itertools
import os
import re
import socket
import stat
import tempfile
from dataclasses import dataclass
from pathlib import Path

from whiztap.analyzer.errors import WhiztapError
from whiztap.sniffer.nettext import AddressError, is_loopback, parse_address, show_address

DEFAULT = "default"  # what ``--control`` without a value stands for: a socket in the runtime folder
SOCKET_GLOB = "control-*.sock"
TOKEN_CHARS = re.compile(r"[A-Za-z0-9._~+/=-]{1,512}")  # RFC 6750's token68: safe in a header
_serial = itertools.count(1)


class EndpointError(WhiztapError, ValueError):
    """An endpoint that cannot be used; the message is one line for the user."""


@dataclass(frozen=True)
class Endpoint:
    """A Unix socket ``path`` ("": a new one in the runtime folder, named when
    the server starts), or TCP ``host:port`` with its bearer ``token`` (None:
    the server makes one at start)."""

    path: str | None = None
    host: str = "127.0.0.1"
    port: int = 0
    token: str | None = None

    @property
    def unix(self) -> bool:
        return self.path is not None

    def __str__(self) -> str:
        if self.path is None:
            return show_address(self.host, self.port)
        return self.path or f"a socket in {runtime_dir()}"

    @property
    def loopback(self) -> bool:
        """Whether only this machine can reach it (a Unix socket, or a loopback address)."""
        return self.unix or is_loopback(self.host)


def parse_endpoint(text: str, what: str = "--control", default_host: str = "127.0.0.1") -> Endpoint:
    """An endpoint as typed: a PATH (it holds a '/' or ends in .sock) is a Unix
    socket; ``[HOST:]PORT`` or ``http://HOST:PORT`` is TCP (the URL form is how
    ``whiztap record`` prints it).  EndpointError naming ``what`` if neither."""
    if text == DEFAULT:
        return Endpoint(path="")
    if text.startswith("http://"):
        text = text.removeprefix("http://").rstrip("/")
    elif "/" in text or text.endswith(".sock"):
        return Endpoint(path=os.path.abspath(os.path.expanduser(text)))
    try:
        host, port = parse_address(text, default_host, what)
    except AddressError as e:
        raise EndpointError(f"{e} (or a socket PATH)") from None
    return Endpoint(host=host, port=port)


def check_token(token: str, what: str = "the control token") -> str:
    """``token`` if a header can carry it as it is (RFC 6750 token68 characters)."""
    if not TOKEN_CHARS.fullmatch(token):
        raise EndpointError(f"{what} may hold only letters, digits and ._~+/=- (at most 512), "
                            f"got {len(token)} characters")
    return token


# -- the runtime folder -------------------------------------------------------------------------


def runtime_dir() -> Path:
    """The folder of this user's default control sockets (not created)."""
    base = os.environ.get("XDG_RUNTIME_DIR")
    if base and os.path.isabs(base):
        return Path(base) / "whiztap"
    return Path(tempfile.gettempdir()) / f"whiztap-{os.getuid()}"


def private_dir(create: bool) -> Path | None:
    """The runtime folder, made mode 0700 if ``create``; None if it does not
    exist and is not to be made.  EndpointError when it is not this user's
    alone (a symbolic link, another owner, open to group or others)."""
    folder = runtime_dir()
    if create:
        try:
            folder.mkdir(mode=0o700, parents=False)
        except FileExistsError:
            pass
        except OSError as e:
            raise EndpointError(f"cannot make {folder}: {e.strerror or e}") from None
    try:
        st = os.lstat(folder)
    except FileNotFoundError:
        return None
    if not stat.S_ISDIR(st.st_mode) or st.st_uid != os.getuid() or st.st_mode & 0o077:
        raise EndpointError(f"{folder} is not a folder only you can open (owner uid {st.st_uid}, mode "
                            f"{stat.S_IMODE(st.st_mode):o}); remove it, or give --control PATH")
    return folder


def default_socket_path() -> Path:
    """A new socket name in the runtime folder (made if need be): one per
    server, so that several recorders of one user never meet.  Sockets that
    killed recorders left there are removed first."""
    folder = private_dir(create=True)
    assert folder is not None  # made just now
    _sweep(folder)
    n = next(_serial)
    return folder / (f"control-{os.getpid()}.sock" if n == 1 else f"control-{os.getpid()}-{n}.sock")


def _sweep(folder: Path) -> None:
    """Remove the sockets whose process is gone and that nobody serves.  Both
    are asked: a socket another server has bound but not yet listens on
    refuses connections too, but its process is alive."""
    for path in folder.glob(SOCKET_GLOB):
        pid = path.name.removeprefix("control-").removesuffix(".sock").split("-")[0]
        if not pid.isdigit() or _alive(int(pid)):
            continue
        with contextlib.suppress(OSError):
            if socket_state(path) == "stale":
                path.unlink()


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # someone else's: alive
        return True
    return True


def live_sockets() -> list[Path]:
    """The default sockets a server answers on now, oldest name first (a
    socket left by a killed recorder refuses connections and is skipped)."""
    folder = private_dir(create=False)
    if folder is None:
        return []
    return [path for path in sorted(folder.glob(SOCKET_GLOB)) if socket_state(path) == "live"]


def socket_state(path: Path | str) -> str:
    """"live" (something accepts connections there), "stale" (a socket
    nobody serves), "missing", or "other" (not a socket)."""
    try:
        if not stat.S_ISSOCK(os.lstat(path).st_mode):
            return "other"
    except FileNotFoundError:
        return "missing"
    with socket.socket(socket.AF_UNIX, socket.SOCK_STREAM) as probe:
        probe.settimeout(1.0)
        try:
            probe.connect(str(path))
        except OSError as e:
            if e.errno in (errno.ECONNREFUSED, errno.ENOENT):
                return "stale"
            raise
    return "live"
