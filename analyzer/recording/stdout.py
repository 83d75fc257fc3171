"""Standard output that goes away while whiztap still has work to finish.

A reader that leaves (``| head``: EPIPE) or a terminal that closes (EIO) must
not stop a recording half-written, nor make the interpreter's last flush fail
with a traceback.  The command line (its reports and status lines) and the
writer process (its status lines to the proxy) both stop talking the same way.
"""

from __future__ import annotations

import os


def drop_stdout() -> None:
    """Point file descriptor 1 at /dev/null: later writes, and the final flush, go nowhere."""
    devnull = os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    os.close(devnull)
