"""TLS for the zenoh transport: a private CA and certificates for tests and configs, and the zenoh
configuration fragment that turns TLS (optionally mutual TLS) on.

Certificates (X.509 v3, RFC 5280) are made with ``cryptography``: ECDSA P-256 keys, SHA-256
signatures; the CA has ``BasicConstraints(ca=True)``; leaf certificates carry
``SubjectAlternativeName`` entries (DNS names and IP addresses -- rustls, which zenoh uses,
checks the SAN, not the CN) and both ``serverAuth`` and ``clientAuth`` extended key usage so one
certificate serves a router's listener and a client's mTLS identity.

zenoh 1.x keys (``transport/link/tls/...``, see zenoh's DEFAULT_CONFIG.json5):
``root_ca_certificate`` (CA file used to verify the other side), ``listen_private_key`` /
``listen_certificate`` (the listener's identity), ``connect_private_key`` /
``connect_certificate`` (the connector's identity, needed with mTLS), ``enable_mtls``,
``verify_name_on_connect``. Endpoints are ``tls/127.0.0.1:PORT``.
"""
from __future__ import annotations

import datetime as _dt
import ipaddress
from dataclasses import dataclass
from pathlib import Path

from cryptography import x509
from cryptography.hazmat.primitives import hashes, serialization
from cryptography.hazmat.primitives.asymmetric import ec
from cryptography.x509.oid import ExtendedKeyUsageOID, NameOID

TLS_PREFIX = "transport/link/tls/"


@dataclass
class CertPair:
    """PEM files of one identity: certificate and its private key."""
    cert_path: Path
    key_path: Path


def _name(common_name: str) -> x509.Name:
    return x509.Name([x509.NameAttribute(NameOID.ORGANIZATION_NAME, "v2xpos"),
                      x509.NameAttribute(NameOID.COMMON_NAME, common_name)])


def _write_key(key: ec.EllipticCurvePrivateKey, path: Path) -> None:
    path.write_bytes(key.private_bytes(serialization.Encoding.PEM,
                                       serialization.PrivateFormat.PKCS8,
                                       serialization.NoEncryption()))
    path.chmod(0o600)


def _now() -> _dt.datetime:
    return _dt.datetime.now(_dt.timezone.utc)


def make_ca(out_dir: str | Path, name: str = "v2xpos test CA", days: int = 30) -> CertPair:
    """Self-signed CA certificate ``out_dir/ca.pem`` and its key ``ca.key``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    key = ec.generate_private_key(ec.SECP256R1())
    now = _now()
    cert = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(_name(name))
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=True, path_length=0), critical=True)
            .add_extension(x509.KeyUsage(digital_signature=True, key_cert_sign=True, crl_sign=True,
                                         content_commitment=False, key_encipherment=False,
                                         data_encipherment=False, key_agreement=False,
                                         encipher_only=False, decipher_only=False), critical=True)
            .add_extension(x509.SubjectKeyIdentifier.from_public_key(key.public_key()), critical=False)
            .sign(key, hashes.SHA256()))
    pair = CertPair(out / "ca.pem", out / "ca.key")
    pair.cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, pair.key_path)
    return pair


def issue_cert(ca: CertPair, out_dir: str | Path, name: str,
               dns_names: tuple[str, ...] = ("localhost",),
               ip_addresses: tuple[str, ...] = ("127.0.0.1",), days: int = 30) -> CertPair:
    """Leaf certificate ``out_dir/<name>.pem`` + ``<name>.key`` signed by ``ca``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    ca_cert = x509.load_pem_x509_certificate(ca.cert_path.read_bytes())
    ca_key = serialization.load_pem_private_key(ca.key_path.read_bytes(), password=None)
    key = ec.generate_private_key(ec.SECP256R1())
    sans: list[x509.GeneralName] = [x509.DNSName(d) for d in dns_names]
    sans += [x509.IPAddress(ipaddress.ip_address(a)) for a in ip_addresses]
    now = _now()
    cert = (x509.CertificateBuilder().subject_name(_name(name)).issuer_name(ca_cert.subject)
            .public_key(key.public_key()).serial_number(x509.random_serial_number())
            .not_valid_before(now - _dt.timedelta(minutes=5))
            .not_valid_after(now + _dt.timedelta(days=days))
            .add_extension(x509.BasicConstraints(ca=False, path_length=None), critical=True)
            .add_extension(x509.SubjectAlternativeName(sans), critical=False)
            .add_extension(x509.ExtendedKeyUsage([ExtendedKeyUsageOID.SERVER_AUTH,
                                                  ExtendedKeyUsageOID.CLIENT_AUTH]), critical=False)
            .add_extension(x509.AuthorityKeyIdentifier.from_issuer_public_key(ca_key.public_key()),
                           critical=False)
            .sign(ca_key, hashes.SHA256()))
    pair = CertPair(out / f"{name}.pem", out / f"{name}.key")
    pair.cert_path.write_bytes(cert.public_bytes(serialization.Encoding.PEM))
    _write_key(key, pair.key_path)
    return pair


@dataclass
class TestPki:
    """A CA with one router (listener) and one client identity, all on disk."""
    ca: CertPair
    router: CertPair
    client: CertPair


def make_test_pki(out_dir: str | Path) -> TestPki:
    """CA + ``router`` + ``client`` certificates valid for localhost / 127.0.0.1."""
    ca = make_ca(out_dir)
    return TestPki(ca, issue_cert(ca, out_dir, "router"), issue_cert(ca, out_dir, "client"))


def zenoh_tls_settings(ca_cert: str | Path, listen: CertPair | None = None,
                       connect: CertPair | None = None, mtls: bool = False,
                       verify_name: bool = True) -> dict[str, object]:
    """``{zenoh config key: value}`` for TLS, ready for ``LinkConfig.extra_json5`` or
    ``zenoh.Config.insert_json5(key, json.dumps(value))``.

    ``listen``: identity presented by a listening side; ``connect``: identity presented when
    connecting. ``mtls`` must be set on both sides: the listener then demands, and the connector
    presents, a certificate signed by ``ca_cert``.
    """
    out: dict[str, object] = {TLS_PREFIX + "root_ca_certificate": str(ca_cert),
                              TLS_PREFIX + "verify_name_on_connect": bool(verify_name)}
    if listen is not None:
        out[TLS_PREFIX + "listen_certificate"] = str(listen.cert_path)
        out[TLS_PREFIX + "listen_private_key"] = str(listen.key_path)
    if connect is not None:
        out[TLS_PREFIX + "connect_certificate"] = str(connect.cert_path)
        out[TLS_PREFIX + "connect_private_key"] = str(connect.key_path)
    if mtls:
        out[TLS_PREFIX + "enable_mtls"] = True
    return out


def tls_endpoint(port: int, host: str = "127.0.0.1") -> str:
    """``tls/HOST:PORT`` locator."""
    if not 0 < int(port) < 65536:
        raise ValueError(f"port {port} out of range 1..65535")
    return f"tls/{host}:{int(port)}"
