"""A site's transport credentials: the site CA, per-process TLS certificates and the machines'
command keys (``slinger certs``; ``slinger up`` makes them on loopback by itself).

Layout of a site directory (every private file mode 0600)::

    <site_dir>/ca.crt, ca.key                 the site CA (ECDSA P-256, 10 years)
    <site_dir>/certs/<cn>.crt, <cn>.key        one per process: CN "server", "router", "worker",
                                               "runtime-<id>", "plant-<id>" (2 years)
    <site_dir>/machines/<id>/command.key       the machine's 32-byte command key, 64 hex digits

Certificates carry subjectAltNames DNS:localhost, IP:127.0.0.1 and every ``--ip`` given (Zenoh
checks the listening peer's name against the endpoint it connects to) and both TLS usages
(serverAuth, clientAuth): in a Zenoh peer mesh every process both listens and connects. The CN
is what Zenoh access control matches (``cert_common_names``, runtime/zenoh_session.py).

Making a site is idempotent: existing files are kept (so keys survive restarts); only missing
ones are created, with the existing CA. Crypto: the ``cryptography`` package (X.509 builder).
"""

from __future__ import annotations

import argparse
import datetime as dt
import ipaddress
import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from runtime.command_auth import new_key, write_key
from runtime.protocol.keys import validate_machine_id

log = logging.getLogger(__name__)

CA_DAYS = 3650
LEAF_DAYS = 730
SITE_ROLES = ("server", "router", "worker")
LOOPBACK_NAMES = ("localhost",)
LOOPBACK_IPS = ("127.0.0.1",)


def runtime_cn(machine_id: str) -> str:
    return f"runtime-{validate_machine_id(machine_id)}"


def plant_cn(machine_id: str) -> str:
    return f"plant-{validate_machine_id(machine_id)}"


@dataclass(frozen=True)
class Site:
    """Paths of a site directory (see the module docstring)."""

    root: Path

    @property
    def ca_cert(self) -> Path:
        return self.root / "ca.crt"

    @property
    def ca_key(self) -> Path:
        return self.root / "ca.key"

    def cert(self, cn: str) -> Path:
        return self.root / "certs" / f"{cn}.crt"

    def key(self, cn: str) -> Path:
        return self.root / "certs" / f"{cn}.key"

    def command_key(self, machine_id: str) -> Path:
        return self.root / "machines" / validate_machine_id(machine_id) / "command.key"


def _write_private(path: Path, data: bytes) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _write_pair(key_path: Path, cert_path: Path, key: ec.EllipticCurvePrivateKey, cert: x509.Certificate) -> None:
    _write_private(key_path, key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                               serialization.NoEncryption()))
    _write_private(cert_path, cert.public_bytes(serialization.Encoding.PEM))


def _builder(subject: x509.Name, issuer: x509.Name, public_key, days: int) -> x509.CertificateBuilder:
    now = dt.datetime.now(dt.UTC)
    return (x509.CertificateBuilder().subject_name(subject).issuer_name(issuer).public_key(public_key)
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=days)))


def _name(cn: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "Slinger site"), x509.NameAttribute(NameOID.COMMON_NAME, cn)])


def _ensure_ca(site: Site) -> tuple[ec.EllipticCurvePrivateKey, x509.Certificate]:
    if site.ca_cert.is_file() and site.ca_key.is_file():
        key = serialization.load_pem_private_key(site.ca_key.read_bytes(), password=None)
        if not isinstance(key, ec.EllipticCurvePrivateKey):
            raise ValueError(f"{site.ca_key}: the site CA key is not an elliptic-curve key")
        return key, x509.load_pem_x509_certificate(site.ca_cert.read_bytes())
    key = ec.generate_private_key(ec.SECP256R1())
    name = _name("Slinger site CA")
    cert = (_builder(name, name, key.public_key(), CA_DAYS)
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True, content_commitment=False,
                                         key_encipherment=False, data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    _write_pair(site.ca_key, site.ca_cert, key, cert)
    log.info("created site CA %s", site.ca_cert)
    return key, cert


def _issue(site: Site, ca_key, ca_cert: x509.Certificate, cn: str, ips: Sequence[str], names: Sequence[str]) -> None:
    key = ec.generate_private_key(ec.SECP256R1())
    sans = [x509.DNSName(n) for n in names] + [x509.IPAddress(ipaddress.ip_address(ip)) for ip in ips]
    cert = (_builder(_name(cn), ca_cert.subject, key.public_key(), LEAF_DAYS)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    _write_pair(site.key(cn), site.cert(cn), key, cert)
    log.info("issued certificate %s (SANs %s)", site.cert(cn), ", ".join([*names, *ips]))


def make_site(site_dir: str | Path, machine_ids: Sequence[str], ips: Sequence[str] = (), names: Sequence[str] = ()) -> Site:
    """Create what is missing of a site: CA, certificates of the site roles and of every
    machine's runtime and plant, and every machine's command key.

    Args:
        site_dir: the site directory (created 0700).
        machine_ids: machine ids ([A-Za-z0-9_-]{1,64}).
        ips: extra IP addresses for the subjectAltNames (besides 127.0.0.1).
        names: extra DNS names for the subjectAltNames (besides localhost).

    Raises:
        ValueError: a bad machine id or IP address.
    """
    ids = [validate_machine_id(m) for m in machine_ids]
    all_ips = list(dict.fromkeys([*LOOPBACK_IPS, *(str(ipaddress.ip_address(ip)) for ip in ips)]))
    all_names = list(dict.fromkeys([*LOOPBACK_NAMES, *names]))
    site = Site(Path(site_dir))
    site.root.mkdir(parents=True, exist_ok=True)
    os.chmod(site.root, 0o700)
    ca_key, ca_cert = _ensure_ca(site)
    for cn in [*SITE_ROLES, *(f(m) for m in ids for f in (runtime_cn, plant_cn))]:
        if not (site.cert(cn).is_file() and site.key(cn).is_file()):
            _issue(site, ca_key, ca_cert, cn, all_ips, all_names)
    for m in ids:
        if not site.command_key(m).is_file():
            write_key(site.command_key(m), new_key())
            log.info("created command key of machine %s", m)
    return site


def build_parser(parser: argparse.ArgumentParser) -> None:
    """Arguments of ``slinger certs``."""
    parser.add_argument("--site-dir", type=Path, required=True, help="site directory (created; existing files are kept)")
    parser.add_argument("--machines", nargs="+", required=True, help="machine ids, e.g. m1 m2")
    parser.add_argument("--ip", action="append", default=[], help="extra IP address in the certificates (repeatable)")
    parser.add_argument("--dns", action="append", default=[], help="extra DNS name in the certificates (repeatable)")


def run(args: argparse.Namespace) -> int:
    """``slinger certs``: make the site; 2 on bad input."""
    try:
        site = make_site(args.site_dir, args.machines, args.ip, args.dns)
    except ValueError as e:
        log.error("cannot make the site: %s", e)
        return 2
    log.info("site %s ready: CA %s, certificates in %s, command keys in %s", site.root, site.ca_cert,
             site.root / "certs", site.root / "machines")
    return 0
