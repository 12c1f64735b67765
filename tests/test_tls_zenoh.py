"""Zenoh over TLS on loopback with certificates made by the test; mTLS refuses unknown clients."""
from __future__ import annotations

import threading
import time

import pytest
from cryptography import x509

from v2xpos import tls
from v2xpos.launch import free_tcp_port
from v2xpos.link import Link, LinkConfig, LinkError


def _exchange(router_cfg: LinkConfig, client_cfg: LinkConfig, n: int = 20, wait_s: float = 3.0) -> list[bytes]:
    got: list[bytes] = []
    done = threading.Event()

    def on(payload, key, att, t):
        got.append(payload)
        if len(got) >= n:
            done.set()

    with Link(router_cfg) as router:
        router.subscribe("v2xpos/tls/test", on)
        with Link(client_cfg) as client:
            pub = client.publisher("v2xpos/tls/test")
            deadline = time.monotonic() + wait_s
            i = 0
            while not done.is_set() and time.monotonic() < deadline:
                pub.put(f"m{i}".encode())
                i += 1
                time.sleep(0.02)
    return got


def test_certificates_have_the_fields_rustls_checks(tmp_path):
    pki = tls.make_test_pki(tmp_path)
    ca = x509.load_pem_x509_certificate(pki.ca.cert_path.read_bytes())
    leaf = x509.load_pem_x509_certificate(pki.router.cert_path.read_bytes())
    assert ca.extensions.get_extension_for_class(x509.BasicConstraints).value.ca
    san = leaf.extensions.get_extension_for_class(x509.SubjectAlternativeName).value
    assert "localhost" in san.get_values_for_type(x509.DNSName)
    assert [str(a) for a in san.get_values_for_type(x509.IPAddress)] == ["127.0.0.1"]
    leaf.verify_directly_issued_by(ca)
    assert pki.router.key_path.stat().st_mode & 0o077 == 0


@pytest.mark.slow
def test_zenoh_tls_and_mtls_on_loopback(tmp_path):
    pki = tls.make_test_pki(tmp_path / "pki")
    port = free_tcp_port()
    ep = tls.tls_endpoint(port)
    # as a service config table would give it ([link] mode/listen/extra_json5)
    router = LinkConfig.from_dict({"mode": "router", "listen": [ep],
                                   "extra_json5": tls.zenoh_tls_settings(pki.ca.cert_path, listen=pki.router,
                                                                         mtls=True)}, "master.toml: [link]")
    client = LinkConfig(mode="client", connect=[ep],
                        extra_json5=tls.zenoh_tls_settings(pki.ca.cert_path, connect=pki.client,
                                                           mtls=True))
    got = _exchange(router, client)
    assert len(got) >= 20 and got[0].startswith(b"m")

    # a client whose certificate comes from another CA is refused by the mTLS router
    rogue = tls.make_ca(tmp_path / "rogue")
    rogue_client = tls.issue_cert(rogue, tmp_path / "rogue", "client")
    port2 = free_tcp_port()
    ep2 = tls.tls_endpoint(port2)
    router2 = LinkConfig(mode="router", listen=[ep2],
                         extra_json5=tls.zenoh_tls_settings(pki.ca.cert_path, listen=pki.router,
                                                            mtls=True))
    settings = tls.zenoh_tls_settings(pki.ca.cert_path, connect=rogue_client, mtls=True)
    settings.update({"connect/timeout_ms": 1500, "connect/exit_on_failure": True})
    bad = LinkConfig(mode="client", connect=[ep2], extra_json5=settings)
    with Link(router2):
        with pytest.raises(LinkError, match="tls/127.0.0.1"):
            Link(bad)


def test_tls_endpoint_validation():
    assert tls.tls_endpoint(7447) == "tls/127.0.0.1:7447"
    with pytest.raises(ValueError):
        tls.tls_endpoint(0)
