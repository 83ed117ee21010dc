"""The etcd test server (tests/support/etcd.py): it serves, stops, comes back on its ports, and speaks TLS."""

from __future__ import annotations

import json
import ssl
import urllib.error
import urllib.request
from collections.abc import Callable

import pytest
from support.certs import CertificateFiles, certificates
from support.etcd import EtcdServer

__all__ = ["certificates"]


def _health(url: str, context: ssl.SSLContext | None = None) -> bool:
    with urllib.request.urlopen(url, timeout=5, context=context) as reply:
        return bool(json.loads(reply.read())["health"] == "true")


def test_etcd_serves_stops_and_comes_back_empty(etcd: EtcdServer) -> None:
    health = f"http://{etcd.endpoint}/health"
    assert _health(health)
    etcd.stop()
    assert not etcd.running
    with pytest.raises(urllib.error.URLError):
        _health(health)
    etcd.start(wipe=True)
    assert _health(health)
    etcd.kill()
    assert etcd.proc is not None and etcd.proc.returncode == -9


def test_etcd_with_tls_asks_for_a_client_certificate(
    etcd_server: Callable[..., EtcdServer], certificates: CertificateFiles
) -> None:
    etcd = etcd_server(tls=certificates)
    assert etcd.url.startswith("etcds://")
    context = ssl.create_default_context(cafile=str(certificates.ca))
    context.load_cert_chain(certificates.clients["alice"].cert, certificates.clients["alice"].key)
    assert _health(f"https://{etcd.endpoint}/health", context)
