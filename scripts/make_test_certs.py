#!/usr/bin/env python3
"""Generate a throwaway certificate authority and TLS certificates for a zenoh deployment.

For tests, demos and private networks only: the CA key is written next to the
certificates, nothing is password protected, and the default lifetime is short. For a
real deployment use your organisation's PKI; the layout below is what the zenoh configs
in ``deploy/zenoh/`` expect.

Files written into the output folder (PEM; keys are PKCS#8, mode 0600)::

    ca.pem          ca-key.pem           the certificate authority (self-signed)
    router.pem      router-key.pem       the zenoh router (CN "router")
    <name>.pem      <name>-key.pem       one per service, CN = <name> (default io, tracker, mapper, poses)

Every leaf certificate is signed by the CA, carries the subject alternative names given
by ``hosts`` (default ``localhost`` and ``127.0.0.1``) and both the serverAuth and
clientAuth extended key usages, so the same certificate works for a process that listens
(router, peer) and for one that connects (client, peer). The common name (CN) of each
certificate is the identity zenoh access control matches with ``cert_common_names``.

Usage::

    python scripts/make_test_certs.py certs/                   # CA, router, io, tracker, mapper, poses
    python scripts/make_test_certs.py certs/ --names io mapper --hosts localhost 127.0.0.1 router
    python scripts/make_test_certs.py certs/ --configs         # also certs/zenoh/*.json5 with absolute paths
    python scripts/make_test_certs.py certs/ --hosts localhost 127.0.0.1 zenoh --configs --config-prefix /certs

Library use (tests)::

    from scripts.make_test_certs import make_test_certs
    paths = make_test_certs(tmp_path)      # -> CertPaths
    paths.ca, paths.leaf["io"].cert, paths.leaf["io"].key
"""
from __future__ import annotations

import argparse
import datetime as _dt
import ipaddress
import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterable, Optional, Sequence

try:
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID
except ImportError as _e:  # pragma: no cover - exercised only without the dev extra
    raise ImportError("scripts/make_test_certs.py needs the 'cryptography' package "
                      "(pip install -e '.[dev]' or pip install cryptography)") from _e

DEFAULT_NAMES = ("io", "tracker", "mapper", "poses")
DEFAULT_HOSTS = ("localhost", "127.0.0.1")
ROUTER_NAME = "router"
_NAME_RE = re.compile(r"^[A-Za-z0-9_.-]{1,64}$")
_REPO = Path(__file__).resolve().parents[1]
CONFIG_TEMPLATES = _REPO / "deploy" / "zenoh"


@dataclass(frozen=True)
class KeyPair:
    """Paths of one PEM certificate and its PEM private key."""

    cert: Path
    key: Path


@dataclass(frozen=True)
class CertPaths:
    """Everything :func:`make_test_certs` wrote. ``leaf`` maps a common name to its files
    and always contains ``"router"``."""

    folder: Path
    ca: Path
    ca_key: Path
    leaf: dict[str, KeyPair] = field(default_factory=dict)

    @property
    def router(self) -> KeyPair:
        return self.leaf[ROUTER_NAME]


def _new_key() -> ec.EllipticCurvePrivateKey:
    return ec.generate_private_key(ec.SECP256R1())


def _san(hosts: Iterable[str]) -> x509.SubjectAlternativeName:
    names: list[x509.GeneralName] = []
    for h in hosts:
        try:
            names.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            names.append(x509.DNSName(h))
    return x509.SubjectAlternativeName(names)


def _write(path: Path, data: bytes, private: bool = False) -> None:
    """Write atomically; private files are created with mode 0600."""
    tmp = path.with_name(path.name + ".tmp")
    flags = os.O_WRONLY | os.O_CREAT | os.O_TRUNC
    fd = os.open(tmp, flags, 0o600 if private else 0o644)
    try:
        os.write(fd, data)
    finally:
        os.close(fd)
    os.replace(tmp, path)


def _key_pem(key: ec.EllipticCurvePrivateKey) -> bytes:
    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def make_ca(common_name: str = "fmapping test CA", days: int = 30,
            now: Optional[_dt.datetime] = None) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A self-signed CA certificate (basicConstraints CA:true, pathlen 0) and its key."""
    now = now or _dt.datetime.now(_dt.timezone.utc)
    key = _new_key()
    name = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])
    cert = (
        x509.CertificateBuilder()
        .subject_name(name).issuer_name(name)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _dt.timedelta(minutes=5))
        .not_valid_after(now + _dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                     content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .sign(key, hashes.SHA256())
    )
    return cert, key


def make_leaf(common_name: str, ca_cert: x509.Certificate, ca_key: ec.EllipticCurvePrivateKey,
              hosts: Sequence[str] = DEFAULT_HOSTS, days: int = 30,
              now: Optional[_dt.datetime] = None) -> tuple[x509.Certificate, ec.EllipticCurvePrivateKey]:
    """A CA-signed end-entity certificate usable as TLS server and client (serverAuth + clientAuth)."""
    if not _NAME_RE.match(common_name):
        raise ValueError(f"certificate name must match [A-Za-z0-9_.-]{{1,64}}, got {common_name!r}")
    if not hosts:
        raise ValueError("at least one host name or IP address is needed for the subjectAltName")
    now = now or _dt.datetime.now(_dt.timezone.utc)
    key = _new_key()
    cert = (
        x509.CertificateBuilder()
        .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)]))
        .issuer_name(ca_cert.subject)
        .public_key(key.public_key())
        .serial_number(x509.random_serial_number())
        .not_valid_before(now - _dt.timedelta(minutes=5))
        .not_valid_after(now + _dt.timedelta(days=days))
        .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
        .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=False, crl_sign=False,
                                     content_commitment=False, key_encipherment=False,
                                     data_encipherment=False, key_agreement=False,
                                     encipher_only=False, decipher_only=False), critical=True)
        .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                              ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
        .add_extension(_san(hosts), critical=False)
        .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
        .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                       critical=False)
        .sign(ca_key, hashes.SHA256())
    )
    return cert, key


def make_test_certs(out_dir: str | os.PathLike, names: Sequence[str] = DEFAULT_NAMES,
                    hosts: Sequence[str] = DEFAULT_HOSTS, days: int = 30,
                    ca_name: str = "fmapping test CA") -> CertPaths:
    """Write a fresh CA, a ``router`` certificate and one certificate per name into ``out_dir``.

    Existing files of the same names are replaced (a new CA each call: certificates from
    two calls do not trust each other). Returns the paths written.
    """
    if days < 1:
        raise ValueError(f"days must be >= 1, got {days}")
    names = list(dict.fromkeys([ROUTER_NAME, *names]))
    for n in names:
        if not _NAME_RE.match(n):
            raise ValueError(f"certificate name must match [A-Za-z0-9_.-]{{1,64}}, got {n!r}")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    now = _dt.datetime.now(_dt.timezone.utc)
    ca_cert, ca_key = make_ca(ca_name, days, now)
    paths = CertPaths(folder=out, ca=out / "ca.pem", ca_key=out / "ca-key.pem")
    _write(paths.ca, ca_cert.public_bytes(serialization.Encoding.PEM))
    _write(paths.ca_key, _key_pem(ca_key), private=True)
    for n in names:
        cert, key = make_leaf(n, ca_cert, ca_key, hosts, days, now)
        kp = KeyPair(cert=out / f"{n}.pem", key=out / f"{n}-key.pem")
        _write(kp.cert, cert.public_bytes(serialization.Encoding.PEM))
        _write(kp.key, _key_pem(key), private=True)
        paths.leaf[n] = kp
    return paths


def render_configs(cert_dir: str | os.PathLike, out_dir: Optional[str | os.PathLike] = None,
                   prefix: Optional[str] = None, templates: Path = CONFIG_TEMPLATES) -> list[Path]:
    """Copy ``deploy/zenoh/*.json5`` to ``out_dir`` (default ``<cert_dir>/zenoh``) with every
    ``"certs/`` path prefix replaced by ``prefix`` (default: the absolute certificate folder;
    e.g. ``/certs`` for a container that mounts the folder there), so the configs work from
    any working directory. Returns the files written."""
    cert_dir = Path(cert_dir).resolve()
    prefix = (prefix if prefix is not None else cert_dir.as_posix()).rstrip("/")
    if not prefix or any(c in prefix for c in '"\\\n'):
        raise ValueError(f"certificate path prefix must be a non-empty path without quotes, got {prefix!r}")
    out = Path(out_dir) if out_dir is not None else cert_dir / "zenoh"
    files = sorted(templates.glob("*.json5"))
    if not files:
        raise FileNotFoundError(f"no *.json5 templates in {templates}")
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for f in files:
        text = f.read_text().replace('"certs/', f'"{prefix}/')
        target = out / f.name
        _write(target, text.encode())
        written.append(target)
    return written


def main(argv: Optional[Sequence[str]] = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", nargs="?", default="certs", help="output folder (default: certs)")
    p.add_argument("--names", nargs="+", default=list(DEFAULT_NAMES),
                   help="service certificates to make besides 'router' (default: io tracker mapper poses)")
    p.add_argument("--hosts", nargs="+", default=list(DEFAULT_HOSTS),
                   help="DNS names / IP addresses put in every certificate's subjectAltName "
                        "(default: localhost 127.0.0.1); add the router's host name for docker")
    p.add_argument("--days", type=int, default=30, help="validity in days (default 30)")
    p.add_argument("--configs", action="store_true",
                   help="also write <out>/zenoh/*.json5: deploy/zenoh configs with absolute certificate paths")
    p.add_argument("--config-prefix", default=None, metavar="DIR",
                   help="with --configs: certificate folder as the services will see it "
                        "(default: the absolute output folder; e.g. /certs in a container)")
    a = p.parse_args(argv)
    try:
        paths = make_test_certs(a.out, a.names, a.hosts, a.days)
        print(f"wrote CA {paths.ca} and certificates for {', '.join(paths.leaf)} into {paths.folder}")
        if a.configs:
            for f in render_configs(a.out, prefix=a.config_prefix):
                print(f"wrote {f}")
    except (ValueError, OSError) as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
