"""Certificates made at test time (no network, no files shipped): a CA, certificates for ASAC's roles
signed by it, and a second, unrelated CA for "the wrong CA" cases.

Usage::

    pki = Pki(tmp_path)                        # writes ca.crt and wrong-ca.crt
    learner = pki.issue("learner")             # learner.crt / learner.key, DNS SAN "learner"
    local = pki.issue("local", "actor", "learner", "replay", "evolver")   # one certificate, every role
    stranger = pki.issue("replay", ca="wrong") # a replay certificate from the wrong CA
    uri = pki.issue("uri", sans=[x509.UniformResourceIdentifier("evolver")], common_name="evolver")  # no DNS SAN
    old = pki.issue("old", "actor", expired=True)  # its validity ended an hour ago
    learner.cert, learner.key, pki.ca          # paths, for --tls_cert / --tls_key / --tls_ca

Role names travel as DNS subject alternative names: that is what ds/net/security.py checks (docs/security.md section 3).
Keys are EC P-256: generated in milliseconds.
"""

from __future__ import annotations

import datetime
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID


@dataclass(frozen=True)
class Issued:
    cert: Path
    key: Path


@dataclass
class _Authority:
    key: ec.EllipticCurvePrivateKey
    cert: x509.Certificate
    path: Path


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _validity(builder: x509.CertificateBuilder, expired: bool = False) -> x509.CertificateBuilder:
    now = datetime.datetime.now(datetime.UTC)
    hour = datetime.timedelta(hours=1)
    if expired:  # valid for a day that ended an hour ago
        return builder.not_valid_before(now - 25 * hour).not_valid_after(now - hour)
    return builder.not_valid_before(now - hour).not_valid_after(now + 24 * hour)


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    path.write_bytes(
        key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8, serialization.NoEncryption())
    )


class Pki:
    """Two independent CAs in ``folder`` (``ca`` and ``wrong_ca``) and :meth:`issue` for leaf certificates."""

    def __init__(self, folder: Path) -> None:
        self.folder = folder
        folder.mkdir(parents=True, exist_ok=True)
        self._cas = {name: self._authority(name) for name in ("ca", "wrong-ca")}
        self.ca = self._cas["ca"].path
        self.wrong_ca = self._cas["wrong-ca"].path

    def _authority(self, name: str) -> _Authority:
        key = ec.generate_private_key(ec.SECP256R1())
        builder = _validity(x509.CertificateBuilder())
        cert = (
            builder.subject_name(_name(f"ASAC test {name}"))
            .issuer_name(_name(f"ASAC test {name}"))
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(
                x509.KeyUsage(False, False, False, False, False, True, True, False, False), critical=True
            )  # keyCertSign, cRLSign
            .sign(key, hashes.SHA256())
        )
        path = self.folder / f"{name}.crt"
        path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        return _Authority(key, cert, path)

    def issue(
        self,
        name: str,
        *roles: str,
        ca: str = "ca",
        sans: Sequence[x509.GeneralName] | None = None,
        common_name: str | None = None,
        expired: bool = False,
    ) -> Issued:
        """``<name>.crt`` and ``<name>.key``, signed by ``ca`` ("ca" or "wrong"), naming ``roles`` (default:
        ``name``) as DNS SANs, usable as server and as client certificate. ``sans`` replaces those
        subject alternative names (e.g. ``[x509.UniformResourceIdentifier("evolver")]``: no DNS SAN);
        ``common_name`` replaces the subject CN (default: ``name``); ``expired``: its validity ended an hour ago."""
        authority = self._cas["wrong-ca" if ca == "wrong" else "ca"]
        key = ec.generate_private_key(ec.SECP256R1())
        if sans is None:
            sans = [x509.DNSName(r) for r in roles or (name,)]
        cert = (
            _validity(x509.CertificateBuilder(), expired)
            .subject_name(_name(common_name or name))
            .issuer_name(authority.cert.subject)
            .public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(
                x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                critical=False,
            )
            .sign(authority.key, hashes.SHA256())
        )
        stem = name if ca == "ca" else f"{name}-wrong-ca"
        issued = Issued(self.folder / f"{stem}.crt", self.folder / f"{stem}.key")
        issued.cert.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
        _write_key(key, issued.key)
        return issued


def replace_file(path: Path, data: bytes) -> None:
    """Write ``data`` next to ``path`` and move it over ``path``, as a Kubernetes Secret volume replaces its
    files (a role never reads one half-written)."""
    fresh = path.with_name(path.name + ".new")
    fresh.write_bytes(data)
    os.replace(fresh, path)


class RoleFiles:
    """One role's credential files in a folder of its own (its host): the token file and its TLS
    certificate, key and CA, replaced as an operator (or cert-manager) rotates them."""

    def __init__(self, folder: Path, issued: Issued, ca: Path, token: bytes) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.token, self.cert, self.key, self.ca = (folder / n for n in ("token", "tls.crt", "tls.key", "ca.pem"))
        self.tokens(token)
        self.use(issued)
        self.trust(ca)

    def tokens(self, *tokens: bytes) -> None:
        replace_file(self.token, b"".join(t + b"\n" for t in tokens))

    def use(self, issued: Issued) -> None:
        replace_file(self.key, issued.key.read_bytes())
        replace_file(self.cert, issued.cert.read_bytes())

    def trust(self, *cas: Path) -> None:
        replace_file(self.ca, b"".join(ca.read_bytes() for ca in cas))

    def tls_flags(self) -> list[str]:
        return ["--tls_cert", str(self.cert), "--tls_key", str(self.key), "--tls_ca", str(self.ca)]

    def flags(self) -> list[str]:
        """``main_ds.py`` flags naming these files."""
        return ["--override", f"net.token_file={self.token}", *self.tls_flags()]
