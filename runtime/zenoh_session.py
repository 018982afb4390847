"""Opening Zenoh sessions the same way everywhere (runtime, plant, server, tests).

The configuration is built once from data (zenoh-python examples habit) with explicit
endpoints; multicast scouting is off by default so that nothing joins a session by accident on a
shared network. Endpoints look like ``tcp/127.0.0.1:7447`` or, with TLS, ``tls/127.0.0.1:7447``.

TLS (issue 8): with :class:`TlsFiles` the session uses the site CA as the only root
(``transport/link/tls/root_ca_certificate``), presents its own certificate both when listening
and when connecting, requires one from every peer (``enable_mtls``) and checks the listening
peer's name against the endpoint (``verify_name_on_connect``). A peer without a certificate of
the site CA cannot open a link. On top, Zenoh access control (``access_control``, built by
runtime.zenoh_acl from the certificates' common names) says which process may send what.

Topology notes: in ``peer`` mode two processes exchange data only over a direct link (one
listens, the other connects to it; gossip lets peers that *listen* find each other through a
common peer). A fleet uses a Zenoh router: every process runs in ``client`` mode and connects to
it. Pitfalls: a session with Python-callback subscribers must be closed (use it as a context
manager) or the interpreter hangs at exit; a peer that hangs without closing its link is only
noticed after the transport lease (``transport/link/tx/lease``, default 10 s).
"""

from __future__ import annotations

import argparse
import json
import logging
import secrets
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import zenoh

log = logging.getLogger(__name__)

MODES = ("peer", "client", "router")


@dataclass(frozen=True)
class TlsFiles:
    """PEM files of one process: the site CA certificate, its certificate and private key.

    The site directory layout (server/site/certs.py): ``<site>/ca.crt``, ``<site>/certs/<cn>.crt``
    and ``<site>/certs/<cn>.key``.
    """

    ca: Path
    cert: Path
    key: Path

    @classmethod
    def from_site(cls, site_dir: str | Path, cn: str) -> TlsFiles:
        site = Path(site_dir)
        return cls(site / "ca.crt", site / "certs" / f"{cn}.crt", site / "certs" / f"{cn}.key")

    def check(self) -> TlsFiles:
        """Return self if every file exists.

        Raises:
            FileNotFoundError: naming the first missing file.
        """
        for p in (self.ca, self.cert, self.key):
            if not Path(p).is_file():
                raise FileNotFoundError(f"TLS file {p} does not exist (make the site with `slinger certs`)")
        return self

    def settings(self) -> dict:
        """The ``transport/link/tls/*`` settings for mutual TLS."""
        paths = {"ca": str(self.ca), "cert": str(self.cert), "key": str(self.key)}
        prefix = "transport/link/tls/"
        return {
            prefix + "root_ca_certificate": paths["ca"],
            prefix + "listen_certificate": paths["cert"],
            prefix + "listen_private_key": paths["key"],
            prefix + "connect_certificate": paths["cert"],
            prefix + "connect_private_key": paths["key"],
            prefix + "enable_mtls": True,
            prefix + "verify_name_on_connect": True,
        }


def zenoh_config(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    tls: TlsFiles | None = None,
    access_control: dict | None = None,
) -> zenoh.Config:
    """A zenoh.Config from explicit settings.

    Args:
        mode: "peer", "client" or "router".
        listen: endpoints to listen on (empty: do not listen).
        connect: endpoints to connect to.
        multicast_scouting: enable UDP multicast discovery (off by default).
        tls: mutual-TLS files (use ``tls/`` endpoints), or None.
        access_control: a Zenoh ``access_control`` section (runtime.zenoh_acl.site_acl), or None.

    Raises:
        ValueError: for an unknown mode or a non-string endpoint.
        FileNotFoundError: a TLS file is missing.
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
    if tls is not None:
        settings.update(tls.check().settings())
    if access_control is not None:
        settings["access_control"] = access_control
    conf = zenoh.Config()
    for key, value in settings.items():
        conf.insert_json5(key, json.dumps(value))
    return conf


def open_session(
    mode: str = "peer",
    listen: Sequence[str] = (),
    connect: Sequence[str] = (),
    multicast_scouting: bool = False,
    tls: TlsFiles | None = None,
    access_control: dict | None = None,
) -> zenoh.Session:
    """Open a session with :func:`zenoh_config`; use it as a context manager (closes on exit).

    Raises:
        ValueError, FileNotFoundError: see zenoh_config.
        zenoh.ZError: if an endpoint cannot be listened on.
    """
    return zenoh.open(zenoh_config(mode, listen, connect, multicast_scouting, tls, access_control))


CLAIM_WAIT_S = 1.5
"""How long a starting runtime or plant listens for other holders and claimants of its machine."""


class Claimed(Exception):
    """The machine already has a holder, or an earlier claimant started at the same time."""


def new_claim(now_s: float | None = None) -> str:
    """A start claim ``<ms since the epoch, 13 digits>-<8 random hex digits>`` (keys.CLAIM_RE):
    claims sort by start time, ties at random."""
    ms = int((time.time() if now_s is None else now_s) * 1000)
    return f"{ms:013d}-{secrets.token_hex(4)}"


def claim_exclusive(session: zenoh.Session, alive_key: str, claim_key, wait_s: float = CLAIM_WAIT_S,
                    claim: str | None = None):
    """Claim a machine for this process, race-free between processes that start at once.

    1. Listen (liveliness subscribers with history) for the holder's token ``alive_key`` and for
       every claim token ``claim_key("*")``.
    2. Declare this process's claim token ``claim_key(claim)`` (``claim`` from :func:`new_claim`).
    3. Wait ``wait_s`` (tokens already known arrive at once; those of processes that start within
       the window arrive within it, in a peer mesh after gossip links them).
    4. If the holder's token was seen, or a live claim that sorts before ours (earlier start; same
       millisecond: the random part decides, the same way in every process), undeclare ours and
       raise :class:`Claimed`. Else declare ``alive_key`` and return ``(alive_token, claim_token)``;
       the caller keeps both for its life (later claimants see the earlier claim too, even if
       their clock is behind, because they also see the holder's token).

    Two processes that start at the same instant thus both see each other's claim after the
    wait, and exactly one (the earlier claim) goes on. The assumption: liveliness tokens reach
    every participant within ``wait_s``; should that fail (a partitioned network), the epoch fence
    (the machine follows only the newest runtime epoch) still keeps one runtime driving it.

    Raises:
        Claimed: with the reason (who holds or claims the machine).
    """
    claim = claim or new_claim()
    claims: dict[str, bool] = {}
    holder = threading.Event()
    lock = threading.Lock()
    prefix = claim_key("*")[:-1]

    def on_claim(sample) -> None:
        with lock:
            claims[str(sample.key_expr)[len(prefix):]] = sample.kind == zenoh.SampleKind.PUT

    def on_alive(sample) -> None:
        if sample.kind == zenoh.SampleKind.PUT:
            holder.set()

    subs = [session.liveliness().declare_subscriber(alive_key, on_alive, history=True),
            session.liveliness().declare_subscriber(claim_key("*"), on_claim, history=True)]
    mine = session.liveliness().declare_token(claim_key(claim))
    try:
        holder.wait(wait_s)
        with lock:
            earlier = sorted(c for c, live in claims.items() if live and c < claim)
        if holder.is_set() or earlier:
            mine.undeclare()
            raise Claimed(f"claimed by another process starting at the same time (claim {earlier[0]} before ours {claim})"
                          if earlier else "held by a running process")
        return session.liveliness().declare_token(alive_key), mine
    finally:
        for sub in subs:
            sub.undeclare()


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """``--connect/--listen/--mode`` and the TLS options of a process's Zenoh session."""
    parser.add_argument("--connect", action="append", default=[], help="Zenoh endpoint to connect to, e.g. tls/127.0.0.1:7447 (repeatable)")
    parser.add_argument("--listen", action="append", default=[], help="Zenoh endpoint to listen on (repeatable)")
    parser.add_argument("--mode", default="peer", choices=("peer", "client"), help="Zenoh session mode")
    parser.add_argument("--tls-dir", type=Path, default=None,
                        help="site directory of `slinger certs`: use mutual TLS with <dir>/ca.crt and this process's "
                             "<dir>/certs/<cn>.crt/.key, and the site's access control")
    parser.add_argument("--tls-ca", type=Path, default=None, help="CA certificate (overrides --tls-dir's)")
    parser.add_argument("--tls-cert", type=Path, default=None, help="this process's certificate (overrides --tls-dir's)")
    parser.add_argument("--tls-key", type=Path, default=None, help="this process's private key (overrides --tls-dir's)")
    parser.add_argument("--acl-machines", nargs="*", default=None,
                        help="machine ids the site's access control names (default: this process's machine)")


def tls_files(args: argparse.Namespace, cn: str) -> TlsFiles | None:
    """TlsFiles from ``--tls-dir`` and/or explicit ``--tls-ca/--tls-cert/--tls-key``, or None.

    Raises:
        ValueError: only some explicit files given without --tls-dir.
        FileNotFoundError: a file is missing.
    """
    explicit = (args.tls_ca, args.tls_cert, args.tls_key)
    if args.tls_dir is None and not any(explicit):
        return None
    if args.tls_dir is None and not all(explicit):
        raise ValueError("give --tls-dir, or all of --tls-ca, --tls-cert and --tls-key")
    if args.tls_dir is None:
        return TlsFiles(args.tls_ca, args.tls_cert, args.tls_key).check()
    base = TlsFiles.from_site(args.tls_dir, cn)
    return TlsFiles(args.tls_ca or base.ca, args.tls_cert or base.cert, args.tls_key or base.key).check()


def session_options(args: argparse.Namespace, cn: str, machine_ids: Sequence[str] = ()) -> dict:
    """Keyword arguments of :func:`open_session` for a process with certificate CN ``cn``
    from the arguments of :func:`add_session_arguments`. With TLS, the site's access control
    for ``--acl-machines`` (default ``machine_ids``) is enabled.

    Raises:
        ValueError, FileNotFoundError: see tls_files.
    """
    from runtime.zenoh_acl import site_acl

    tls = tls_files(args, cn)
    acl_ids = args.acl_machines if getattr(args, "acl_machines", None) else list(machine_ids)
    return {"mode": args.mode, "listen": args.listen, "connect": args.connect, "tls": tls,
            "access_control": site_acl(acl_ids) if tls is not None else None}


def undeclare_all(declarations: list) -> None:
    """Undeclare Zenoh subscribers, queryables, publishers or tokens; one already closed with its
    session is skipped (logged at debug level). The list is emptied."""
    for d in declarations:
        try:
            d.undeclare()
        except Exception:  # already closed with the session
            log.debug("undeclare failed", exc_info=True)
    declarations.clear()
