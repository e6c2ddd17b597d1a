"""`cvxnav certs`: a private CA, one certificate per stage and one for the router, and their Zenoh configs.

Mutual TLS: every link is TLS, the router only accepts clients whose certificate this CA signed, and
clients only trust a router this CA signed (name checked against its subjectAltName). Zenoh's access
control then matches the certificate's common name against the least privilege the wiring table
(`schemas.wiring`) gives it (`grants`): each key may be put only by the process the table names as its
publisher, each process subscribes only to what it reads, holds a liveliness token only under its own
name and puts only its own status; the monitor and the operator (`cvxnav status`) only read. Everything
else is denied by default. A certificate from another CA never gets a link; a valid certificate with
another name gets a link that carries nothing.

Keys are ECDSA P-256 in PKCS#8 PEM, certificates X.509 v3 (what rustls, Zenoh's TLS, requires: the
leaf has CA:false and a subjectAltName; the CN is only used by the access-control subjects).
"""

from __future__ import annotations

import datetime as dt
import ipaddress
import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

from schemas.wiring import PROCESSES, TOPICS, alive_key, every_key, key, status_key
from services.shell.zenoh_config import NO_SHARED_MEMORY

ROUTER = "router"
OPERATOR = "operator"  # the name `cvxnav status` connects with
DEFAULT_ROUTER_HOSTS = ("localhost", "127.0.0.1", ROUTER)
VALIDITY_DAYS = 365
ACL_MESSAGES = (
    "put", "delete", "declare_subscriber", "query", "reply", "declare_queryable",
    "liveliness_token", "declare_liveliness_subscriber", "liveliness_query",
)
# One permission of the router's access control: (flow seen from the router, message, key expression).
# "ingress" is what the certificate's session sends the router, "egress" what the router sends it.
Grant = tuple[str, str, str]


def pipeline_names() -> tuple[str, ...]:
    """Who may speak under the prefix: every stage of the wiring table, the monitor, the operator."""
    return (*PROCESSES, OPERATOR)


@dataclass(frozen=True)
class Issued:
    """A certificate and its private key."""

    certificate: x509.Certificate
    private_key: ec.EllipticCurvePrivateKey

    def write(self, *, cert_path: Path, key_path: Path) -> None:
        cert_path.write_bytes(self.certificate.public_bytes(serialization.Encoding.PEM))
        key_path.write_bytes(self.private_key.private_bytes(
            serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption()))
        os.chmod(key_path, 0o600)


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "cvxnav"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def make_ca(*, common_name: str = "cvxnav CA", now: dt.datetime | None = None) -> Issued:
    """A self-signed CA that signs only leaf certificates (path length 0)."""
    now = now or dt.datetime.now(dt.timezone.utc)
    key = ec.generate_private_key(ec.SECP256R1())
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name)).issuer_name(_name(common_name))
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=VALIDITY_DAYS))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return Issued(certificate=cert, private_key=key)


def issue(*, ca: Issued, common_name: str, hosts: Sequence[str] = (), now: dt.datetime | None = None) -> Issued:
    """A leaf for ``common_name`` usable as TLS server and client; ``hosts`` become DNS/IP subjectAltNames."""
    now = now or dt.datetime.now(dt.timezone.utc)
    key = ec.generate_private_key(ec.SECP256R1())
    alt_names: list[x509.GeneralName] = []
    for host in hosts or (common_name,):
        try:
            alt_names.append(x509.IPAddress(ipaddress.ip_address(host)))
        except ValueError:
            alt_names.append(x509.DNSName(host))
    cert = (
        x509.CertificateBuilder()
        .subject_name(_name(common_name)).issuer_name(ca.certificate.subject)
        .public_key(key.public_key()).serial_number(x509.random_serial_number())
        .not_valid_before(now - dt.timedelta(minutes=5)).not_valid_after(now + dt.timedelta(days=VALIDITY_DAYS))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                     content_commitment=False, key_encipherment=False, data_encipherment=False,
                                     key_agreement=False, encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                       critical=False)
        .add_extension(x509.SubjectAlternativeName(alt_names), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca.private_key.public_key()),
                       critical=False)
        .sign(ca.private_key, hashes.SHA256())
    )
    return Issued(certificate=cert, private_key=key)


def grants(name: str, *, key_prefix: str = "cvxnav") -> frozenset[Grant]:
    """What the certificate ``name`` may do, derived from the wiring table; nothing for a name it lacks.

    Keys are granted for any robot id (``<key_prefix>/*/...``): a certificate is a role, not a robot.
    A publisher may put its keys and be told who subscribes to them (a declared publisher sends only
    towards known subscribers); a reader may subscribe to them and be sent them. A latched key's
    publisher answers queries on it, and its readers may ask. Every process holds its token and puts its status only
    under its own name; the sources that follow liveliness may watch the tokens, the processes that
    hear statuses may read them. The operator (`cvxnav status`) reads every key and asks the tokens.
    """
    space = f"{key_prefix}/*"
    allowed: set[Grant] = set()
    if name == OPERATOR:
        allowed |= {("ingress", "declare_subscriber", every_key(space)), ("egress", "put", every_key(space)),
                    ("ingress", "liveliness_query", alive_key(space)), ("egress", "liveliness_token", alive_key(space))}
        return frozenset(allowed)
    spec = PROCESSES.get(name)
    if spec is None:
        return frozenset()
    for written in [key(space, topic) for topic in spec.publishes] + [status_key(space, name)]:
        allowed |= {("ingress", "put", written), ("egress", "declare_subscriber", written)}
    read = [key(space, topic) for topic in spec.subscribes] + ([status_key(space)] if spec.hears_statuses else [])
    for topic_key in read:
        allowed |= {("ingress", "declare_subscriber", topic_key), ("egress", "put", topic_key)}
    for topic in spec.publishes:
        if TOPICS[topic].latched:
            allowed |= {("ingress", "declare_queryable", key(space, topic)), ("egress", "query", key(space, topic)),
                        ("ingress", "reply", key(space, topic))}
    for topic in spec.subscribes:
        if TOPICS[topic].latched:
            allowed |= {("ingress", "query", key(space, topic)), ("egress", "reply", key(space, topic))}
    allowed.add(("ingress", "liveliness_token", alive_key(space, name)))
    if spec.watches:
        allowed |= {("ingress", "declare_liveliness_subscriber", alive_key(space)),
                    ("egress", "liveliness_token", alive_key(space))}
    return frozenset(allowed)


def access_control(*, names: Sequence[str], key_prefix: str = "cvxnav") -> dict:
    """Zenoh 1.x ``access_control``: deny by default; each named certificate gets its ``grants``.

    One subject and one policy per certificate; its grants become one rule per (flow, message), listing
    the keys (Zenoh allows a message when a rule's key expression includes the message's key).
    """
    rules, subjects, policies = [], [], []
    for name in names:
        by_verb: dict[tuple[str, str], list[str]] = {}
        for flow, message, key_expr in sorted(grants(name, key_prefix=key_prefix)):
            by_verb.setdefault((flow, message), []).append(key_expr)
        if not by_verb:
            continue
        ids = []
        for (flow, message), key_exprs in by_verb.items():
            ids.append(f"{name}-{flow}-{message}")
            rules.append({"id": ids[-1], "messages": [message], "flows": [flow], "permission": "allow",
                          "key_exprs": key_exprs})
        subjects.append({"id": name, "cert_common_names": [name]})
        policies.append({"id": f"{name}-policy", "rules": ids, "subjects": [name]})
    return {"enabled": True, "default_permission": "deny", "rules": rules, "subjects": subjects,
            "policies": policies}


def router_config(*, cert_dir: Path, listen: Sequence[str], names: Sequence[str], key_prefix: str = "cvxnav") -> dict:
    """The router's Zenoh config: TLS listener that demands a client certificate, plus access control."""
    return {
        "mode": "router",
        "listen": {"endpoints": list(listen)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {**NO_SHARED_MEMORY, "link": {"tls": {
            "root_ca_certificate": str(cert_dir / "ca.pem"),
            "listen_certificate": str(cert_dir / f"{ROUTER}.pem"),
            "listen_private_key": str(cert_dir / f"{ROUTER}.key"),
            "enable_mtls": True,
        }}},
        "access_control": access_control(names=names, key_prefix=key_prefix),
    }


def client_config(*, cert_dir: Path, name: str, connect: Sequence[str]) -> dict:
    """A stage's Zenoh config: a client of the router over TLS, presenting its own certificate."""
    return {
        "mode": "client",
        "connect": {"endpoints": list(connect)},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {**NO_SHARED_MEMORY, "link": {"tls": {
            "root_ca_certificate": str(cert_dir / "ca.pem"),
            "connect_certificate": str(cert_dir / f"{name}.pem"),
            "connect_private_key": str(cert_dir / f"{name}.key"),
            "enable_mtls": True,
            "verify_name_on_connect": True,
        }}},
    }


def missing_files(*, cert_dir: Path, names: Sequence[str]) -> list[Path]:
    """What a run with the router and these clients needs from ``cert_dir`` (CA, certificates, keys) but lacks."""
    needed = [cert_dir / "ca.pem"] + [cert_dir / f"{name}.{ext}" for name in (ROUTER, *names) for ext in ("pem", "key")]
    return [path for path in needed if not path.is_file()]


def write_deployment(*, out_dir: Path, router_hosts: Sequence[str] = DEFAULT_ROUTER_HOSTS, port: int = 7447,
                     key_prefix: str = "cvxnav", names: Sequence[str] | None = None) -> list[Path]:
    """CA, router and per-name certificates, and a ready Zenoh config per name, into ``out_dir``."""
    out_dir = out_dir.resolve()
    out_dir.mkdir(parents=True, exist_ok=True)
    names = tuple(names or pipeline_names())
    ca = make_ca()
    ca.write(cert_path=out_dir / "ca.pem", key_path=out_dir / "ca.key")
    issue(ca=ca, common_name=ROUTER, hosts=router_hosts).write(cert_path=out_dir / f"{ROUTER}.pem",
                                                               key_path=out_dir / f"{ROUTER}.key")
    written = [out_dir / "ca.pem", out_dir / f"{ROUTER}.pem"]
    router_json = out_dir / f"{ROUTER}.json5"
    router_json.write_text(json.dumps(router_config(cert_dir=out_dir, listen=[f"tls/0.0.0.0:{port}"], names=names,
                                                    key_prefix=key_prefix), indent=2) + "\n")
    written.append(router_json)
    for name in names:
        issue(ca=ca, common_name=name).write(cert_path=out_dir / f"{name}.pem", key_path=out_dir / f"{name}.key")
        config_path = out_dir / f"{name}.json5"
        config_path.write_text(json.dumps(client_config(cert_dir=out_dir, name=name,
                                                        connect=[f"tls/{router_hosts[0]}:{port}"]), indent=2) + "\n")
        written += [out_dir / f"{name}.pem", config_path]
    return written
