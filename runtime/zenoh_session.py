"""Opening Zenoh sessions the same way everywhere (runtime, plant, server, tests).

The configuration is built once from data (zenoh-python examples habit) with explicit
endpoints; multicast scouting is off by default so that nothing joins a session by accident on a
shared network. Endpoints look like ``tcp/127.0.0.1:7447``.

Topology notes: in ``peer`` mode two processes exchange data only over a direct link (one
listens, the other connects to it; gossip lets peers that *listen* find each other through a
common peer). A fleet uses a Zenoh router: every process runs in ``client`` mode and connects to
it. Pitfalls: a session with Python-callback subscribers must be closed (use it as a context
manager) or the interpreter hangs at exit; a peer that hangs without closing its link is only
noticed after the transport lease (``transport/link/tx/lease``, default 10 s).
"""

from __future__ import annotations

import json
from typing import Sequence

import zenoh

MODES = ("peer", "client", "router")


def zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
) -> zenoh.Config:
    """A zenoh.Config from explicit settings.

    Args:
        mode: "peer", "client" or "router".
        listen: endpoints to listen on (empty: do not listen).
        connect: endpoints to connect to.
        multicast_scouting: enable UDP multicast discovery (off by default).

    Raises:
        ValueError: for an unknown mode or a non-string endpoint.
    """
    if mode not in MODES:
        raise ValueError(f"zenoh mode must be one of {MODES}, got {mode!r}")
    for ep in (*listen, *connect):
        if not isinstance(ep, str) or "/" not in ep:
            raise ValueError(f"zenoh endpoint must look like 'tcp/host:port', got {ep!r}")
    settings = {
        "mode": mode,
        "listen/endpoints": list(listen),
        "connect/endpoints": list(connect),
        "scouting/multicast/enabled": bool(multicast_scouting),
    }
    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def open_session(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
) -> zenoh.Session:
    """Open a session with :func:`zenoh_config`; use it as a context manager (closes on exit).

    Raises:
        ValueError: see zenoh_config.
        zenoh.ZError: if an endpoint cannot be listened on.
    """
    return zenoh.open(zenoh_config(mode, listen, connect, multicast_scouting))
