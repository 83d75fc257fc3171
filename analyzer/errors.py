"""The one base class of the errors whiztap's own code raises.

Every package (analyzer, sniffer, tui) raises errors of its own kinds, each
with a message that is one line a user can act on.  They all derive from
``WhiztapError``, so the command line's root can tell them from bugs: a
``WhiztapError`` that no command caught is printed as that line with exit
status 2, anything else is an unexpected error.  It lives at the bottom of the
analyzer so that every layer can import it without importing upward.

Exceptions used only to signal between parts of whiztap (a follower told to
stop, a delivery out of step) are not errors and do not derive from it.
"""

from __future__ import annotations


class WhiztapError(Exception):
    """A problem whiztap found and can say in one line: bad input, an
    unreadable file, an unreachable peer, a refused request."""
