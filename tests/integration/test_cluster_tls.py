"""A cluster whose gateways serve mutual TLS: calls are forwarded to the owner over TLS.

Two gateway processes on one real etcd, each serving its gRPC port with the test CA's server
certificate and requiring client certificates. Each has ``[registry] peer_ca`` and a client
certificate of its own (``peer_cert``, CN ``peer``) for forwarding; a third has none, and the
owner refuses what it forwards.
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from pathlib import Path

import grpc
import pytest
from line_device_support import tcp_device
from support.certs import CertificateFiles, make_certificates
from support.etcd import EtcdServer
from support.gateway_process import GatewayProcess, start_gateway
from support.waiting import eventually

from clients import AsyncClient, ClientCredentials
from clients.errors import Unavailable

pytestmark = [pytest.mark.slow, pytest.mark.timeout(120)]


def _config(etcd: EtcdServer, certs: CertificateFiles, gateway: str, *, peer: bool) -> str:
    text = f"""
        [tls]
        cert = "{certs.server.cert}"
        key = "{certs.server.key}"
        client_ca = "{certs.ca}"
        require_client_cert = true

        [registry]
        store = "{etcd.url}"
        store_lease = 2
        gateway_id = "{gateway}"
        peer_ca = "{certs.ca}"
        """
    if peer:
        text += f"""
        peer_cert = "{certs.clients["peer"].cert}"
        peer_key = "{certs.clients["peer"].key}"
        """
    return text


@pytest.fixture
def secure_cluster(
    etcd_server: Callable[..., EtcdServer], tmp_path: Path
) -> Iterator[tuple[CertificateFiles, dict[str, GatewayProcess]]]:
    folder = tmp_path
    certs = make_certificates(folder / "certs", clients=("alice", "peer"))
    etcd = etcd_server()
    alice = certs.clients["alice"]
    ready = grpc.ssl_channel_credentials(
        root_certificates=certs.ca.read_bytes(),
        private_key=alice.key.read_bytes(),
        certificate_chain=alice.cert.read_bytes(),
    )
    gateways: dict[str, GatewayProcess] = {}
    try:
        for gateway, peer in (("gw-a", True), ("gw-b", True), ("gw-c", False)):
            gateways[gateway] = start_gateway(
                folder, _config(etcd, certs, gateway, peer=peer), credentials=ready
            )
        yield certs, gateways
    finally:
        for process in gateways.values():
            process.stop()


def _client(certs: CertificateFiles, gateway: GatewayProcess) -> AsyncClient:
    alice = certs.clients["alice"]
    credentials = ClientCredentials(ca=str(certs.ca), cert=str(alice.cert), key=str(alice.key))
    return AsyncClient(gateway.address, credentials=credentials, timeout=5)


async def test_calls_are_forwarded_to_the_owner_over_mutual_tls(
    secure_cluster: tuple[CertificateFiles, dict[str, GatewayProcess]],
) -> None:
    certs, gateways = secure_cluster
    with tcp_device("--service", "sim-sensor", "--name", "thermo") as (host, port):
        async with (
            _client(certs, gateways["gw-a"]) as a,
            _client(certs, gateways["gw-b"]) as b,
            _client(certs, gateways["gw-c"]) as c,
        ):
            await a.set("registry", "services.thermo", f"tcp://{host}:{port}")
            for client in (b, c):
                await eventually(
                    lambda c=client: c.get("registry", "services.thermo.owner"),
                    lambda owner: owner == "gw-a",
                    what="the owner seen everywhere",
                )
            # gw-b presents its peer certificate: the owner serves what it forwards.
            assert 10.0 < await b.get_number("thermo", "data") < 30.0
            assert await b.set("thermo", "rate_hz", "20") == "20"
            assert await a.get("thermo", "rate_hz") == "20"
            # gw-c has no client certificate for the others: the owner refuses the connection, and
            # the caller hears that the owner cannot be reached, not a wrong answer.
            with pytest.raises(Unavailable):
                await c.get("thermo", "data")
