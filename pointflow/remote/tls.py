"""TLS certificates for Zenoh links: ``pointflow keys NAME --tls --dir certs``.

One certificate authority per deployment signs one certificate per host; every host
trusts that CA only (``zenoh.tls.root_ca``), so with mutual TLS a router or peer accepts
exactly the hosts whose certificate the CA signed. Files, PEM:

- ``ca.pem``: the CA certificate; copy it to every host.
- ``ca-key.pem``: the CA's private key (0600); it signs new certificates; keep it on the
  machine where certificates are made, not on the hosts.
- ``NAME.pem`` and ``NAME-key.pem`` (0600): the host's certificate and private key.

Keys are ECDSA P-256. A certificate names its host in the subject's common name (Zenoh
shows it as the link's certificate name and its access control can match it) and in the
subjectAltName entries Zenoh checks against the address it connects to. The same steps with
the ``openssl`` command are in docs/remote.md.
"""
from __future__ import annotations

import dataclasses
import datetime
import ipaddress
import os
import re
from pathlib import Path

from ..errors import Error

#: Lifetimes: the CA outlives the host certificates it signs.
CA_DAYS = 3650
CERT_DAYS = 825
#: The names a certificate gets when none is given: this host only.
DEFAULT_HOSTS = ("localhost", "127.0.0.1")
_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]*$")


class TlsFileError(Error, ValueError):
    """A certificate or key is missing, exists already, or does not load."""


@dataclasses.dataclass
class Made:
    ca: Path
    ca_key: Path
    certificate: Path
    private_key: Path
    ca_created: bool
    names: list[str]


def _write_private(path: Path, data: bytes) -> None:
    """Create ``path`` readable only by its owner, from the first byte on."""
    fd = os.open(path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
    with os.fdopen(fd, "wb") as f:
        f.write(data)
    os.chmod(path, 0o600)


def _key_pem(key) -> bytes:
    from cryptography.hazmat.primitives import serialization

    return key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                             serialization.NoEncryption())


def _load_ca(ca: Path, ca_key: Path):
    from cryptography import x509
    from cryptography.hazmat.primitives import serialization

    if not ca_key.is_file():
        raise TlsFileError(f"{ca} exists but its key {ca_key} is not here: make certificates where the CA "
                           "key is kept, or move ca.pem away to start a new CA (every host then needs the new one)")
    try:
        cert = x509.load_pem_x509_certificate(ca.read_bytes())
        key = serialization.load_pem_private_key(ca_key.read_bytes(), password=None)
    except (ValueError, TypeError, OSError) as exc:
        raise TlsFileError(f"cannot load the CA {ca} / {ca_key}: {exc}") from None
    if cert.public_key().public_numbers() != key.public_key().public_numbers():
        raise TlsFileError(f"{ca_key} is not the key of {ca}")
    return cert, key


def _new_ca(name: str):
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import NameOID

    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)])
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder().subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(now + datetime.timedelta(days=CA_DAYS))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=False, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=True,
                                         crl_sign=True, encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    return cert, key


def _alt_names(hosts: list[str]):
    from cryptography import x509

    out, seen = [], set()
    for h in hosts:
        if h in seen:
            continue
        seen.add(h)
        try:
            out.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            if not _NAME.match(h):
                raise TlsFileError(f"--host {h!r} is neither an IP address nor a host name") from None
            out.append(x509.DNSName(h))
    return out


def make_certificate(name: str, directory: str | os.PathLike, hosts: list[str] | tuple[str, ...] = (),
                     overwrite: bool = False) -> Made:
    """Write ``NAME.pem`` and ``NAME-key.pem`` into ``directory``, signed by its ``ca.pem``
    (made first, with ``ca-key.pem``, when the folder has none). The certificate is valid
    for ``NAME`` and each of ``hosts`` (names or IP addresses; default: this host only)."""
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    if not name or not _NAME.match(name) or name in ("ca",):
        raise TlsFileError(f"certificate name must be a plain host name (letters, digits, '.', '-', '_'; not 'ca'), "
                           f"got {name!r}")
    d = Path(directory)
    try:
        d.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise TlsFileError(f"cannot create {d}: {exc.strerror or exc}") from None
    ca_path, ca_key_path = d / "ca.pem", d / "ca-key.pem"
    cert_path, key_path = d / f"{name}.pem", d / f"{name}-key.pem"
    if not overwrite and (cert_path.exists() or key_path.exists()):
        raise TlsFileError(f"{cert_path} or {key_path} already exists; pick another name, remove them or add --force")
    names = [name, *(hosts or DEFAULT_HOSTS)]
    alt = _alt_names(names)
    created = not ca_path.exists()
    if created:
        ca_cert, ca_key = _new_ca(f"pointflow CA {d.resolve().name}")
        _write_private(ca_key_path, _key_pem(ca_key))
        ca_path.write_bytes(ca_cert.public_bytes(serialization.Encoding.PEM))
    else:
        ca_cert, ca_key = _load_ca(ca_path, ca_key_path)
    key = ec.generate_private_key(ec.SECP256R1())
    now = datetime.datetime.now(datetime.timezone.utc)
    cert = (x509.CertificateBuilder()
            .subject_name(x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, name)]))
            .issuer_name(ca_cert.subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - datetime.timedelta(minutes=5))
            .not_valid_after(min(now + datetime.timedelta(days=CERT_DAYS), ca_cert.not_valid_after_utc))
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False, key_cert_sign=False,
                                         crl_sign=False, encipher_only=False, decipher_only=False), critical=True)
            # every host is a server (it listens) and a client (it connects)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH, ExtendedKeyUsageOID.CLIENT_AUTH]),
                           critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()), critical=False)
            .sign(ca_key, hashes.SHA256()))
    _write_private(key_path, _key_pem(key))
    cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    return Made(ca_path, ca_key_path, cert_path, key_path, created, names)
