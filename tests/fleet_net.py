"""Test hosts for the fleet topology (tests/fleet_site.py): network namespaces on one bridge, and a
TCP relay that lets them reach the root namespace's PostgreSQL.

* :class:`Net`: a Linux bridge in the root namespace (``10.201.<s>.1/24``, ``<s>`` from the
  site's tag so that two sites do not collide) and one namespace per host, each joined to the
  bridge by a veth pair (``10.201.<s>.<n>`` inside). :meth:`Net.cut` takes a host's link down
  (the bridge side of its veth), :meth:`Net.restore` brings it back. Needs root and iproute2.
* :class:`TcpRelay`: PostgreSQL here listens on 127.0.0.1 only and trusts that address
  (pg_hba ``host all all 127.0.0.1/32 trust``); rather than re-configure and restart a shared
  PostgreSQL, the test relays ``10.201.<s>.1:<port>`` (the bridge address, reachable from every
  host) to ``127.0.0.1:5432`` from the root namespace, so PostgreSQL sees 127.0.0.1 and its
  loopback trust rule applies. A site would instead let PostgreSQL listen on its network with
  ``hostssl ... scram-sha-256`` rules.
"""

from __future__ import annotations

import socket
import subprocess
import threading


def ip(*args: str, ns: str | None = None) -> None:
    """Run ``ip ARGS`` (in namespace ``ns``); raises CalledProcessError with ip's message."""
    argv = ["ip", *(("netns", "exec", ns, "ip") if ns else ()), *args]
    r = subprocess.run(argv, capture_output=True, text=True)
    if r.returncode != 0:
        raise subprocess.CalledProcessError(r.returncode, argv, r.stdout, r.stderr)


class Net:
    """Hosts on one bridge (context manager: :meth:`close` deletes namespaces and links).

    Args:
        tag: a short unique tag (<= 6 characters: interface names have at most 15).
        subnet: the third octet of ``10.201.<subnet>.0/24``.
    """

    def __init__(self, tag: str, subnet: int):
        if not 0 <= subnet <= 255 or len(tag) > 6:
            raise ValueError(f"bad net tag/subnet {tag!r}/{subnet}")
        self.tag, self.subnet = tag, subnet
        self.bridge = f"slb{tag}"
        self.hosts: dict[str, tuple[str, str, str]] = {}  # name -> (namespace, address, bridge-side veth)
        ip("link", "add", "name", self.bridge, "type", "bridge")
        ip("addr", "add", f"{self.gateway}/24", "dev", self.bridge)
        ip("link", "set", self.bridge, "up")

    @property
    def gateway(self) -> str:
        """The root namespace's address on the bridge."""
        return f"10.201.{self.subnet}.1"

    def add_host(self, name: str) -> tuple[str, str]:
        """A new host (namespace + veth on the bridge); returns ``(namespace, address)``."""
        n = len(self.hosts) + 2
        ns, outer, inner, addr = f"slf-{self.tag}-{name}", f"vr{self.tag}{n}", f"vn{self.tag}{n}", f"10.201.{self.subnet}.{n}"
        ip("netns", "add", ns)
        self.hosts[name] = (ns, addr, outer)
        ip("link", "add", outer, "type", "veth", "peer", "name", inner)
        ip("link", "set", inner, "netns", ns)
        ip("link", "set", outer, "master", self.bridge)
        ip("link", "set", outer, "up")
        ip("addr", "add", f"{addr}/24", "dev", inner, ns=ns)
        ip("link", "set", inner, "up", ns=ns)
        ip("link", "set", "lo", "up", ns=ns)
        return ns, addr

    def cut(self, name: str) -> None:
        """Take host ``name``'s link down (the bridge side of its veth)."""
        ip("link", "set", self.hosts[name][2], "down")

    def restore(self, name: str) -> None:
        ip("link", "set", self.hosts[name][2], "up")

    def close(self) -> None:
        for ns, _addr, outer in self.hosts.values():
            subprocess.run(["ip", "link", "del", outer], capture_output=True)
            subprocess.run(["ip", "netns", "del", ns], capture_output=True)
        subprocess.run(["ip", "link", "del", self.bridge], capture_output=True)


class TcpRelay:
    """Relay TCP connections from ``(listen_host, port)`` to ``target`` on daemon threads.

    Args:
        listen_host: address to listen on (port chosen by the system, see ``port``).
        target: ``(host, port)`` to connect each accepted connection to.
    """

    def __init__(self, listen_host: str, target: tuple[str, int]):
        self.target = target
        self.sock = socket.create_server((listen_host, 0))
        self.port = self.sock.getsockname()[1]
        self._closed = False
        threading.Thread(target=self._accept, name="tcp-relay", daemon=True).start()

    def _accept(self) -> None:
        while not self._closed:
            try:
                client, _ = self.sock.accept()
            except OSError:
                return  # closed
            try:
                upstream = socket.create_connection(self.target, timeout=5)
                upstream.settimeout(None)
            except OSError:
                client.close()
                continue
            for a, b in ((client, upstream), (upstream, client)):
                threading.Thread(target=self._pipe, args=(a, b), daemon=True).start()

    @staticmethod
    def _pipe(src: socket.socket, dst: socket.socket) -> None:
        try:
            while data := src.recv(65536):
                dst.sendall(data)
        except OSError:
            pass
        finally:
            for s in (src, dst):
                try:
                    s.shutdown(socket.SHUT_RDWR)
                except OSError:
                    pass
                s.close()

    def close(self) -> None:
        self._closed = True
        self.sock.close()
