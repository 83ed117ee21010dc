"""The gateway's log names TLS as the likely cause when a client and a TLS port do not match: a
plaintext client, a client without a certificate, one with a certificate of another CA, on the
HTTPS port and the line listener; and many bad connections cannot flood the log.

Each client connects from its own loopback address (127.0.0.N) because the log writes at most one
line per address a minute.
"""

from __future__ import annotations

import asyncio
import re
import ssl
import time

import aiohttp
import grpc
import pytest
from support.certs import CertificateFiles, certificates
from support.gateway_process import GatewayProcess, StartGateway
from support.ports import free_port

from gateway.handshake_log import MOST_LINES

__all__ = ["certificates"]

LOG_WAIT = 10.0


def _https_config(certs: CertificateFiles) -> str:
    return f"""
        [tls]
        cert = "{certs.server.cert}"
        key = "{certs.server.key}"
        client_ca = "{certs.ca}"
        require_client_cert = true

        [http]
        tls = true

        [[services]]
        name = "bot"
        type = "sim-robot"
        """


def _start_https(gateway_process: StartGateway, certs: CertificateFiles) -> GatewayProcess:
    alice = certs.clients["alice"]
    credentials = grpc.ssl_channel_credentials(
        root_certificates=certs.ca.read_bytes(),
        private_key=alice.key.read_bytes(),
        certificate_chain=alice.cert.read_bytes(),
    )
    gw = gateway_process(_https_config(certs), credentials=credentials)
    assert gw.http_url.startswith("https://")
    return gw


def _client_context(certs: CertificateFiles, pair: tuple[str, str] | None) -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=str(certs.ca))
    if pair is not None:
        context.load_cert_chain(*pair)
    return context


async def _log_line(gw: GatewayProcess, pattern: str) -> str:
    """The first log line matching ``pattern`` (searched), waited for."""
    wanted = re.compile(pattern)
    deadline = time.monotonic() + LOG_WAIT
    while time.monotonic() < deadline:
        for line in gw.output.splitlines():
            if wanted.search(line):
                return line
        await asyncio.sleep(0.05)
    raise AssertionError(f"no log line matching {pattern!r} in:\n{gw.output[-4000:]}")


async def _get(url: str, source: str, context: ssl.SSLContext | None) -> None:
    """A GET from ``source`` that the gateway refuses in the handshake."""
    connector = aiohttp.TCPConnector(local_addr=(source, 0), ssl=context if context is not None else False)
    async with aiohttp.ClientSession(connector=connector) as http:
        with pytest.raises(aiohttp.ClientError):
            async with http.get(url, timeout=aiohttp.ClientTimeout(total=LOG_WAIT)) as response:
                await response.read()


async def test_a_plaintext_client_on_the_https_port_is_named_with_its_likely_cause(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    gw = _start_https(gateway_process, certificates)
    url = gw.http_url.replace("https://", "http://") + "api/v1/services"
    await _get(url, "127.0.0.2", None)
    line = await _log_line(gw, r"TLS handshake with 127\.0\.0\.2 failed")
    assert " WARNING " in line or '"WARNING"' in line, line
    assert "http.listen" in line
    assert "(HTTP_REQUEST)" in line
    assert "a plaintext client on the TLS port: use https:// and the CA" in line


async def test_a_client_without_a_certificate_is_told_apart_from_one_of_another_ca(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    gw = _start_https(gateway_process, certificates)
    url = gw.http_url + "api/v1/services"
    await _get(url, "127.0.0.3", _client_context(certificates, None))
    foreign = certificates.foreign
    await _get(url, "127.0.0.4", _client_context(certificates, (str(foreign.cert), str(foreign.key))))
    no_cert = await _log_line(gw, r"TLS handshake with 127\.0\.0\.3 failed")
    assert "(PEER_DID_NOT_RETURN_A_CERTIFICATE)" in no_cert
    assert "no client certificate: this port requires one" in no_cert
    assert "require_client_cert" in no_cert
    other_ca = await _log_line(gw, r"TLS handshake with 127\.0\.0\.4 failed")
    assert "(CERTIFICATE_VERIFY_FAILED)" in other_ca
    assert "the client certificate was refused" in other_ca
    # A client with a good certificate is served and adds no line.
    good = certificates.clients["alice"]
    context = _client_context(certificates, (str(good.cert), str(good.key)))
    connector = aiohttp.TCPConnector(local_addr=("127.0.0.5", 0), ssl=context)
    async with aiohttp.ClientSession(connector=connector) as http, http.get(url) as response:
        assert response.status == 200
    assert "127.0.0.5" not in gw.output


async def test_a_silent_client_is_named_when_the_handshake_time_is_over(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    alice = certificates.clients["alice"]
    credentials = grpc.ssl_channel_credentials(
        root_certificates=certificates.ca.read_bytes(),
        private_key=alice.key.read_bytes(),
        certificate_chain=alice.cert.read_bytes(),
    )
    config = "[gateway]\nhandshake_timeout = 0.5\n" + _https_config(certificates)
    gw = gateway_process(config, credentials=credentials)
    host, port = gw.http_address.rsplit(":", 1)
    # A plaintext client of a protocol in which the server speaks first: it waits, sending nothing.
    reader, writer = await asyncio.open_connection(host, int(port), local_addr=("127.0.0.8", 0))
    assert await asyncio.wait_for(reader.read(100), LOG_WAIT) == b""  # closed by the gateway
    writer.close()
    line = await _log_line(gw, r"TLS handshake with 127\.0\.0\.8 failed")
    assert "(no handshake in time)" in line
    assert "a plaintext client waiting for the gateway to speak first" in line


async def test_many_bad_connections_leave_a_bounded_log_with_a_count_of_the_rest(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    gw = _start_https(gateway_process, certificates)
    host, port = gw.http_address.rsplit(":", 1)
    repeats = 5
    sources = [f"127.0.1.{n}" for n in range(1, MOST_LINES + 6)]

    async def knock(source: str) -> None:
        _, writer = await asyncio.open_connection(host, int(port), local_addr=(source, 0))
        writer.write(b"GET / HTTP/1.1\r\nHost: gw\r\n\r\n")
        await writer.drain()
        writer.close()
        await writer.wait_closed()

    for _ in range(repeats):
        for source in sources:
            await knock(source)
    sent = repeats * len(sources)
    await _log_line(gw, r"TLS handshake with 127\.0\.1\.\d+ failed")
    await asyncio.sleep(1.0)  # the last knocks reach the log
    gw.stop()
    lines = [line for line in gw.output.splitlines() if "TLS handshake with" in line]
    assert len(lines) == MOST_LINES, "\n".join(lines)
    named = [re.search(r"with (\S+) failed", line).group(1) for line in lines]  # type: ignore[union-attr]
    assert len(set(named)) == len(named), "one line per address"
    summary = await _log_line(gw, r"more failed TLS handshake\(s\) not logged one by one")
    held_back = int(re.search(r"(\d+) more failed", summary).group(1))  # type: ignore[union-attr]
    assert held_back == sent - MOST_LINES, summary


async def test_a_plaintext_device_on_the_tls_line_listener_is_named_with_its_likely_cause(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    port = free_port()
    gw = gateway_process(f"""
        [gateway]
        line_listen = "127.0.0.1:{port}"
        [tls.line]
        cert = "{certificates.server.cert}"
        key = "{certificates.server.key}"
        client_ca = "{certificates.ca}"

        [[services]]
        name = "bot"
        type = "sim-robot"
        """)
    _, writer = await asyncio.open_connection("127.0.0.1", port, local_addr=("127.0.0.6", 0))
    writer.write(b"SET bot.velocity (0 0 0)\n")
    await writer.drain()
    plaintext = await _log_line(gw, r"TLS handshake with 127\.0\.0\.6 failed")
    writer.close()
    assert "gateway.line_listen" in plaintext
    assert "a plaintext client on the TLS port: connect with TLS and the CA" in plaintext
    # A TLS device without a certificate, where [tls.line] client_ca requires one.
    reader, writer = await asyncio.open_connection(
        "127.0.0.1",
        port,
        local_addr=("127.0.0.7", 0),
        ssl=_client_context(certificates, None),
        server_hostname="localhost",
    )
    assert await asyncio.wait_for(reader.read(100), LOG_WAIT) == b""  # closed: no greeting
    writer.close()
    no_cert = await _log_line(gw, r"TLS handshake with 127\.0\.0\.7 failed")
    assert "(PEER_DID_NOT_RETURN_A_CERTIFICATE)" in no_cert
    assert "this port requires one ([tls.line] client_ca)" in no_cert
