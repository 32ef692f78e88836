"""The service's TLS certificate: self-signed, made on first run and kept, renewed when it expires or
when the address the phones use is not in it.

Browsers give motion sensors only to secure pages, and a phone reaches the laptop by its LAN
address, so the certificate names that address (and ``localhost``). The user accepts it once on the
phone; its SHA-256 fingerprint is printed so they can check that what the phone shows is this one.
"""

from __future__ import annotations

import datetime as _dt
import ipaddress
import logging
import os
import ssl
from dataclasses import dataclass
from pathlib import Path

from capture.clock import MONOTONIC
from capture.errors import ConfigError

log = logging.getLogger(__name__)

CERT_FILE = "serve-cert.pem"
KEY_FILE = "serve-key.pem"
VALID_DAYS = 397  # the longest validity browsers accept for a server certificate
RENEW_BEFORE_DAYS = 30


@dataclass(frozen=True)
class Certificate:
    cert_path: Path
    key_path: Path
    fingerprint: str  # SHA-256, colon-separated hex
    names: tuple[str, ...]
    created: bool

    def server_context(self) -> ssl.SSLContext:
        ctx = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
        ctx.minimum_version = ssl.TLSVersion.TLSv1_2
        try:
            ctx.load_cert_chain(self.cert_path, self.key_path)
        except (OSError, ssl.SSLError) as exc:
            raise ConfigError(f"cannot load the TLS certificate {self.cert_path}: {exc}; delete it and its key to "
                              "make a new one", source=str(self.cert_path)) from None
        return ctx


def _names_of(cert: object) -> set[str]:
    from cryptography import x509

    try:
        san = cert.extensions.get_extension_for_class(x509.SubjectAlternativeName).value  # type: ignore[attr-defined]  # cryptography types .value as the ExtensionType base
    except x509.ExtensionNotFound:
        return set()
    return {str(n) for n in san.get_values_for_type(x509.DNSName)} | {
        str(n) for n in san.get_values_for_type(x509.IPAddress)}


def ensure_certificate(state_dir: Path, hosts: list[str], now: _dt.datetime | None = None) -> Certificate:
    """The certificate in ``state_dir``, made (or remade) so it names every one of ``hosts``.

    Raises:
        ConfigError: the directory is not writable, or the stored files are unreadable.
    """
    from cryptography import x509
    from cryptography.hazmat.primitives import hashes, serialization
    from cryptography.hazmat.primitives.asymmetric import ec
    from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

    now = now or _dt.datetime.fromtimestamp(MONOTONIC.wall_time_s(), _dt.UTC)
    state_dir = Path(state_dir)
    cert_path, key_path = state_dir / CERT_FILE, state_dir / KEY_FILE
    want = {h for h in hosts if h} | {"localhost", "127.0.0.1"}
    if cert_path.exists() and key_path.exists():
        try:
            cert = x509.load_pem_x509_certificate(cert_path.read_bytes())
            names = _names_of(cert)
            fresh = cert.not_valid_after_utc - now > _dt.timedelta(days=RENEW_BEFORE_DAYS)
            if fresh and want <= names:
                return Certificate(cert_path, key_path, cert.fingerprint(hashes.SHA256()).hex(":").upper(),
                                   tuple(sorted(names)), False)
            log.info("TLS certificate %s is %s; making a new one", cert_path,
                     "about to expire" if not fresh else f"missing {sorted(want - names)}")
            want |= names  # keep serving the addresses it already had
        except (OSError, ValueError) as exc:
            log.warning("TLS certificate %s is unreadable (%s); making a new one", cert_path, exc)
    key = ec.generate_private_key(ec.SECP256R1())
    subject = x509.Name([x509.NameAttribute(NameOID.COMMON_NAME, "perfcap serve"),
                         x509.NameAttribute(NameOID.ORGANIZATION_NAME, "perfcap (self-signed)")])
    alt: list[x509.GeneralName] = []
    for h in sorted(want):
        try:
            alt.append(x509.IPAddress(ipaddress.ip_address(h)))
        except ValueError:
            alt.append(x509.DNSName(h))
    cert = (x509.CertificateBuilder()
            .subject_name(subject).issuer_name(subject).public_key(key.public_key())
            .serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=VALID_DAYS))
            .add_extension(x509.SubjectAlternativeName(alt), critical=False)
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH]), critical=False)
            .sign(key, hashes.SHA256()))
    try:
        state_dir.mkdir(parents=True, exist_ok=True, mode=0o700)
        fd = os.open(key_path, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o600)
        with os.fdopen(fd, "wb") as f:
            f.write(key.private_bytes(serialization.Encoding.PEM, serialization.PrivateFormat.PKCS8,
                                      serialization.NoEncryption()))
        cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    except OSError as exc:
        raise ConfigError(f"cannot write the TLS certificate to {state_dir}: {exc}", source=str(state_dir)) from None
    fp = cert.fingerprint(hashes.SHA256()).hex(":").upper()
    log.info("made a self-signed TLS certificate for %s (SHA-256 %s)", ", ".join(sorted(want)), fp)
    return Certificate(cert_path, key_path, fp, tuple(sorted(want)), True)
