"""Machine links: the site's certificates (server/site/certs.py), mutual TLS and the site's Zenoh access
control (runtime/zenoh_acl.py), with in-process sessions on loopback."""

from __future__ import annotations

import argparse
import ipaddress
import os
import time

import pytest
from cryptography import x509
from cryptography.x509.oid import NameOID

from runtime.command_auth import load_key
from runtime.protocol import keys
from runtime.zenoh_acl import machines_in_site, site_acl
from runtime.zenoh_session import TlsFiles, add_session_arguments, open_session, session_options
from server.site import certs
from tests.conftest import free_port, wait_for


@pytest.fixture(scope="module")
def site(tmp_path_factory):
    return certs.make_site(tmp_path_factory.mktemp("site"), ["m1", "m2"], ips=["10.0.0.5"])


def test_site_files_names_and_modes(site):
    cert = x509.load_pem_x509_certificate(site.cert("runtime-m1").read_bytes())
    assert cert.subject.get_attributes_for_oid(NameOID.COMMON_NAME)[0].value == "runtime-m1"
    sans = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert sans.get_values_for_type(x509.DNSName) == ["localhost"]
    assert sans.get_values_for_type(x509.IPAddress) == [ipaddress.ip_address("127.0.0.1"), ipaddress.ip_address("10.0.0.5")]
    ca = x509.load_pem_x509_certificate(site.ca_cert.read_bytes())
    cert.verify_directly_issued_by(ca)
    for cn in ("server", "router", "worker", "runtime-m2", "plant-m1", "plant-m2"):
        assert site.cert(cn).is_file() and os.stat(site.key(cn)).st_mode & 0o777 == 0o600
    assert os.stat(site.ca_key).st_mode & 0o777 == 0o600
    assert len(load_key(site.command_key("m2"))) == 32 and load_key(site.command_key("m1")) != load_key(site.command_key("m2"))


def test_making_a_site_again_keeps_what_exists(site):
    before = {p: p.read_bytes() for p in (site.ca_cert, site.cert("server"), site.command_key("m1"))}
    certs.make_site(site.root, ["m1", "m3"])
    assert all(p.read_bytes() == data for p, data in before.items())
    assert site.command_key("m3").is_file() and site.cert("runtime-m3").is_file()
    with pytest.raises(ValueError):
        certs.make_site(site.root, ["m/1"])
    with pytest.raises(ValueError):
        certs.make_site(site.root, ["m1"], ips=["not-an-ip"])
    parser = argparse.ArgumentParser()
    certs.build_parser(parser)
    assert certs.run(parser.parse_args(["--site-dir", str(site.root), "--machines", "bad id"])) == 2


def test_session_options_from_arguments(site, tmp_path):
    parser = argparse.ArgumentParser()
    add_session_arguments(parser)
    opts = session_options(parser.parse_args(["--tls-dir", str(site.root), "--connect", "tls/127.0.0.1:1"]), "plant-m1", ["m1"])
    assert opts["tls"] == TlsFiles.from_site(site.root, "plant-m1") and opts["access_control"]["enabled"]
    assert session_options(parser.parse_args([]), "plant-m1")["tls"] is None
    with pytest.raises(ValueError, match="all of"):
        session_options(parser.parse_args(["--tls-ca", str(site.ca_cert)]), "plant-m1")
    with pytest.raises(FileNotFoundError, match="slinger certs"):
        session_options(parser.parse_args(["--tls-dir", str(tmp_path)]), "plant-m1")


class Runtime:
    """A runtime-m1 stand-in on a TLS listener with the site ACL: a throw queryable and a state
    subscriber that record what reaches them."""

    def __init__(self, site, endpoint):
        self.queries, self.states = [], []
        self.session = open_session(listen=[endpoint], tls=TlsFiles.from_site(site.root, "runtime-m1"),
                                    access_control=site_acl(["m1", "m2"]))
        self.decls = [
            self.session.declare_queryable(keys.throw("m1"), self._on_query),
            self.session.declare_subscriber(keys.state("m1"), lambda s: self.states.append(s.payload.to_bytes())),
        ]

    def _on_query(self, query):
        self.queries.append(query.payload.to_bytes() if query.payload is not None else b"")
        query.reply(query.key_expr, b"ack")

    def close(self):
        for d in self.decls:
            d.undeclare()
        self.session.close()


def _try(session, tag: bytes) -> list[bytes]:
    """Put a state and query the throw key as ``tag``; return the replies."""
    session.put(keys.state("m1"), tag)
    return [r.ok.payload.to_bytes() for r in session.get(keys.throw("m1"), payload=tag, timeout=1.0) if r.ok is not None]


def test_only_the_server_can_command_and_only_the_plant_can_publish_state(site, tmp_path):
    endpoint = f"tls/127.0.0.1:{free_port()}"
    rt = Runtime(site, endpoint)
    other_ca = certs.make_site(tmp_path / "other-site", ["m1"])
    try:
        outcomes = {}
        peers = {
            "server": dict(tls=TlsFiles.from_site(site.root, "server")),
            "plant-m1": dict(tls=TlsFiles.from_site(site.root, "plant-m1")),
            "worker": dict(tls=TlsFiles.from_site(site.root, "worker")),
            "runtime-m2": dict(tls=TlsFiles.from_site(site.root, "runtime-m2")),
            "server of another CA": dict(tls=TlsFiles.from_site(other_ca.root, "server")),
        }
        for name, kw in peers.items():
            with open_session(connect=[endpoint], **kw) as s:
                time.sleep(0.3)  # let the link and the declarations settle
                outcomes[name] = _try(s, name.encode())
        with open_session(connect=[endpoint.replace("tls/", "tcp/")]) as bare:  # no certificate at all
            time.sleep(0.3)
            outcomes["bare tcp"] = _try(bare, b"bare")
        wait_for(lambda: rt.states, 5, "the plant's state")
        time.sleep(0.3)
    finally:
        rt.close()
    assert outcomes["server"] == [b"ack"] and rt.queries == [b"server"]  # only the server's query got through
    assert all(outcomes[name] == [] for name in outcomes if name != "server"), outcomes
    assert rt.states == [b"plant-m1"]  # only the plant of m1 may publish m1's state


def test_acl_names_every_machine_once():
    acl = site_acl(["m1", "m2", "m1"])
    ids = [r["id"] for r in acl["rules"]]
    assert len(ids) == len(set(ids)) and "runtime-m2-put" in ids and "plant-m1-token" in ids
    assert acl["default_permission"] == "deny"
    with pytest.raises(ValueError):
        site_acl(["*"])


def test_through_a_tls_router_only_the_server_commands(site):
    """Fleet topology: every process a client of the site's router (CN "router"), which enforces
    the site's rules on the links it forwards."""
    endpoint = f"tls/127.0.0.1:{free_port()}"

    def client(cn):
        return open_session("client", connect=[endpoint], tls=TlsFiles.from_site(site.root, cn),
                            access_control=site_acl(["m1"]))

    queries = []
    with open_session("router", listen=[endpoint], tls=TlsFiles.from_site(site.root, "router"),
                      access_control=site_acl(machines_in_site(site.root))):
        with client("runtime-m1") as rt:
            q = rt.declare_queryable(keys.throw("m1"), lambda query: (queries.append(query.payload.to_bytes()),
                                                                       query.reply(query.key_expr, b"ack")))
            replies = {}
            for cn in ("plant-m1", "server"):
                with client(cn) as s:
                    time.sleep(0.3)
                    replies[cn] = [r.ok.payload.to_bytes() for r in s.get(keys.throw("m1"), payload=cn.encode(), timeout=1.0)
                                   if r.ok is not None]
            q.undeclare()
    assert replies == {"plant-m1": [], "server": [b"ack"]} and queries == [b"server"]


def test_slinger_server_session_over_tls(site, tmp_path):
    """``slinger server --tls-dir SITE`` (Settings.zenoh_tls_dir): TLS with the server's
    certificate and the ACL of the site's machines."""
    from server.config import Settings
    from server.services import open_zenoh

    endpoint = f"tls/127.0.0.1:{free_port()}"
    settings = Settings(data_dir=tmp_path, zenoh_listen=[endpoint], zenoh_tls_dir=site.root, viser_enabled=False)
    got = []
    with open_zenoh(settings) as server:
        sub = server.declare_subscriber(keys.state("m2"), lambda s: got.append(s.payload.to_bytes()))
        for cn in ("worker", "plant-m2"):
            with open_session(connect=[endpoint], tls=TlsFiles.from_site(site.root, cn)) as s:
                time.sleep(0.3)
                s.put(keys.state("m2"), cn.encode())
                time.sleep(0.2)
        wait_for(lambda: got, 5, "plant-m2's state")
        sub.undeclare()
    assert got == [b"plant-m2"]
