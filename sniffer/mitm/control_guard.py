"""Who may send the control API a request: the checks made on a request's
head before its body is read or anything is done (docs/faults.md, "Reaching
the control API").

A web page in the user's browser can send requests to any address the
machine reaches, 127.0.0.1 included.  It cannot read the answers of another
origin, but a request that changes something (``POST /inject``) does its harm
unanswered; and a page whose name the attacker re-points at 127.0.0.1 (DNS
rebinding) reads the answers too.  So, on TCP:

- ``Host`` must name this server as a client that typed its address does:
  localhost, 127.0.0.1, [::1] or the bound address (any IP address when bound
  to 0.0.0.0 or ::), with or without the port.  A rebinding page's requests
  carry its own name.
- A request carrying ``Origin`` comes from a web page (browsers add it to
  every cross-origin request and to every POST); nothing whiztap ships sends one.
- A body must say ``Content-Type: application/json``: the only bodies a page
  may send without asking first (a "simple" request) are text/plain, form
  data and multipart.
- Then the bearer token, which a page cannot know.

The first three answer 403, the token 401 (with ``WWW-Authenticate: Bearer``).
Over a Unix socket, which no browser can open and only its user may, there is
no Host worth checking and no token; the Origin and Content-Type checks apply
there too, so one request is refused alike on both.
"""

from __future__ import annotations

import ipaddress
import secrets
from collections.abc import Mapping

from whiztap.sniffer.mitm.control_endpoint import Endpoint
from whiztap.sniffer.mitm.http_api import HttpError

MAX_BODY = 64 << 10
WILDCARDS = frozenset({"0.0.0.0", "::", ""})  # the addresses that mean "every interface"
LOCAL_NAMES = frozenset({"localhost", "127.0.0.1", "::1"})


def check_head(headers: Mapping[bytes, bytes], endpoint: Endpoint, token: str | None) -> None:
    """Raise HttpError (403, 401, 411 or 413) unless a request with these
    ``headers`` (names lower-cased, as h11 gives them) may be read further.
    ``endpoint`` is where it arrived; ``token`` the bearer token it must carry (TCP)."""
    if not endpoint.unix:
        _check_host(headers.get(b"host"), endpoint)
    origin = headers.get(b"origin")
    if origin is not None:
        raise HttpError(403, f"a request from a web page (Origin {_shown(origin)}) is refused: "
                             f"the control API is for whiztap ctl, scripts and curl")
    has_body = b"transfer-encoding" in headers or headers.get(b"content-length", b"0") != b"0"
    media = headers.get(b"content-type", b"").split(b";")[0].strip().lower()
    if (has_body or media) and media != b"application/json":
        raise HttpError(403, f"a body must be Content-Type: application/json, "
                             f"got {_shown(headers.get(b'content-type', b'none'))}")
    if token is not None:
        _check_token(headers.get(b"authorization"), token)
    if b"transfer-encoding" in headers:
        raise HttpError(411, "send the body with a Content-Length (chunked bodies are not taken)")
    length = int(headers.get(b"content-length", b"0"))  # h11 took it only as digits
    if length > MAX_BODY:
        raise HttpError(413, f"the body is {length} bytes; at most {MAX_BODY} are taken")


def _check_host(host: bytes | None, endpoint: Endpoint) -> None:
    if host is None:
        raise HttpError(403, "a request must say Host (this server's address)")
    name = _host_name(host.decode("latin-1").strip().lower())
    if name in LOCAL_NAMES or name == endpoint.host.lower():
        return
    if endpoint.host in WILDCARDS and _is_ip(name):
        return  # a name re-pointed at this machine is a name, never an address
    raise HttpError(403, f"Host {_shown(host)} is not this server's address (a page re-pointed at it?); "
                         f"use localhost or the address it listens on")


def _host_name(text: str) -> str:
    """The name of a Host value without its port: ``[::1]:7000`` -> ``::1``."""
    if text.startswith("["):
        return text[1:].partition("]")[0]
    if text.count(":") == 1:
        return text.partition(":")[0]
    return text


def _is_ip(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def _check_token(authorization: bytes | None, token: str) -> None:
    scheme, _, given = (authorization or b"").partition(b" ")
    if scheme.lower() != b"bearer" or not secrets.compare_digest(given.strip(), token.encode()):
        raise HttpError(401, "the control token is missing or wrong: send 'Authorization: Bearer TOKEN' with "
                             "the token whiztap printed at start (whiztap ctl takes WHIZTAP_CONTROL_TOKEN)")


def _shown(value: bytes) -> str:
    """A header value quoted in a message: short, and as text."""
    text = value.decode("latin-1")
    return repr(text if len(text) <= 60 else text[:60] + "...")
