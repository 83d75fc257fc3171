"""Network things as one-line messages write them: an address, and why a
connection failed (in the system's own words)."""

from __future__ import annotations

import os
import socket


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


def show_address(host: str, port: int) -> str:
    """host:port, with an IPv6 host in brackets."""
    return f"[{host}]:{port}" if ":" in host else f"{host}:{port}"
