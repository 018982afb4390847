"""``slinger router``: the site's Zenoh router (zenoh-python in router mode).

A fleet runs every process (server, runtimes, simulated machines) as a Zenoh ``client`` that
connects to this router; the router forwards between them, so a machine host needs one outbound
link only, and cutting it cuts that machine alone::

    slinger router --listen tcp/0.0.0.0:7447
    slinger router --listen tls/0.0.0.0:7447 --tls-dir SITE   # mutual TLS, CN "router", site ACL

The router holds no application state: restarting it interrupts links, not throws (runtimes
keep results in their outbox until the server acknowledges them).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

from runtime.entrypoint import stop_on_signals
from runtime.zenoh_acl import machines_in_site, site_acl
from runtime.zenoh_session import TlsFiles, open_session

log = logging.getLogger(__name__)
DEFAULT_LISTEN = "tcp/0.0.0.0:7447"


def build_parser(p: argparse.ArgumentParser) -> None:
    p.add_argument("--listen", action="append", default=[], help=f"endpoint to listen on (repeatable; default {DEFAULT_LISTEN})")
    p.add_argument("--connect", action="append", default=[], help="another router to connect to (repeatable)")
    p.add_argument("--tls-dir", type=Path, default=None,
                   help="site directory of `slinger certs`: mutual TLS with the router's certificate and the site's "
                        "access control for the site's machines (it enforces them on every link it forwards)")


def run(args: argparse.Namespace, stop=None) -> int:
    """Serve until SIGINT/SIGTERM; exit code 2 when an endpoint cannot be listened on."""
    listen = args.listen or [DEFAULT_LISTEN]
    stop = stop_on_signals(stop)
    try:
        tls = TlsFiles.from_site(args.tls_dir, "router") if args.tls_dir else None
        acl = site_acl(machines_in_site(args.tls_dir)) if args.tls_dir else None
        session = open_session(mode="router", listen=listen, connect=args.connect, tls=tls, access_control=acl)
    except Exception as e:  # noqa: BLE001  zenoh.ZError: the port is taken or the address unknown
        log.error("router cannot listen on %s: %s", ", ".join(listen), e)
        return 2
    with session:
        log.info("zenoh router %s listening on %s", session.zid(), ", ".join(listen))
        stop.wait()
    log.info("zenoh router stopped")
    return 0
