"""Network things as one-line messages write them: an address, and why a
connection failed (in the system's own words)."""

from __future__ import annotations

import ipaddress
from typing import TYPE_CHECKING
import os
import socket
import struct

from whiztap.analyzer.errors import WhiztapError

if TYPE_CHECKING:
    import asyncio


def reason(e: OSError) -> str:
    """'Connection refused', 'Name or service not known', ...

    asyncio's own text for a refused connection names the call and the address
    ("Connect call failed ('127.0.0.1', 5000)"), which the message already
    says, so the errno's text is used; a name that does not resolve has a
    negative errno of its own numbering, which only ``strerror`` explains.
    """
    if isinstance(e, socket.gaierror) or not e.errno:
        return e.strerror or str(e)
    return os.strerror(e.errno)


LOOPBACK_NAMES = frozenset({"localhost"})


def is_loopback(host: str) -> bool:
    """Whether ``host`` (a name or an address) means this machine only: a
    server bound anywhere else can be reached from other machines."""
    if host.lower() in LOOPBACK_NAMES:
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def show_address(host: str, port: int) -> str:
    """host:port, with an IPv6 host in brackets."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"


class AddressError(WhiztapError, ValueError):
    """An address the user typed is not HOST:PORT; the message is one line for them."""


def parse_address(text: str, default_host: str | None, what: str) -> tuple[str, int]:
    """(host, port) from HOST:PORT, [V6]:PORT, or PORT alone when a default
    host is given: the inverse of ``show_address``.  ``what`` names the
    address in the message (an option, 'target')."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = "", text
    host = host.strip("[]")
    if not host:
        if default_host is None:
            raise AddressError(f"{what} must be HOST:PORT, got {text!r}")
        host = default_host
    if not port.isdigit() or int(port) > 65535:
        raise AddressError(f"{what} needs a port number 0-65535, got {text!r}")
    return host, int(port)

_LINGER_NOW = struct.pack("ii", 1, 0)  # SO_LINGER on, 0 s: close() sends a TCP reset


def arm_reset(transport: asyncio.BaseTransport) -> None:
    """Make the next close of ``transport``'s socket a TCP RST, not a FIN
    (a socket already gone is left as it is); the caller aborts it."""
    sock = transport.get_extra_info("socket")
    if sock is not None:
        try:
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, _LINGER_NOW)
        except OSError:
            pass

