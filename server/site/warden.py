"""The warden of one ``slinger up``: ends its children's process groups when it dies.

``python -m server.site.warden`` reads lines ``+<pgid>`` (a child's process group to guard) and
``-<pgid>`` (gone, forget it) on standard input, whose write end only ``slinger up`` holds. At
end of input (``slinger up`` exited in any way, ``kill -9`` included: the kernel closes its
pipe) it sends SIGTERM to every remembered group that still exists, waits up to
:data:`GRACE_S` for them to end (a runtime puts its valves to neutral on SIGTERM), SIGKILLs
what is left and exits. Keeps its imports to the standard library: it starts in ~30 ms.
"""

from __future__ import annotations

import os
import signal
import sys
import time

GRACE_S = 3.0


def _alive(pgid: int) -> bool:
    try:
        os.killpg(pgid, 0)
        return True
    except (ProcessLookupError, PermissionError):
        return False


def end_groups(pgids: set[int], grace_s: float = GRACE_S) -> None:
    """SIGTERM the groups, wait up to ``grace_s``, SIGKILL the rest."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        for pgid in pgids:
            try:
                os.killpg(pgid, sig)
            except (ProcessLookupError, PermissionError):
                pass
        deadline = time.monotonic() + grace_s
        while sig == signal.SIGTERM and time.monotonic() < deadline and any(_alive(p) for p in pgids):
            time.sleep(0.05)


def main() -> int:
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # outlive a Ctrl-C aimed at the stack
    pgids: set[int] = set()
    for line in sys.stdin:
        line = line.strip()
        if len(line) > 1 and line[1:].isdigit():
            (pgids.add if line[0] == "+" else pgids.discard)(int(line[1:]))
    end_groups({p for p in pgids if _alive(p)})
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
