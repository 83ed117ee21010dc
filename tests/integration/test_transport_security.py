"""Transport security through real gateway processes: TLS and mutual TLS on the gRPC port, SIGHUP
reload, the refusal of a plaintext non-loopback listener, TLS on the line listener."""

from __future__ import annotations

import asyncio
import json
import shutil
import signal
import ssl
import subprocess
import sys
from pathlib import Path

import grpc
import pytest
from support.certs import CertificateFiles, certificates, issue_certificate, make_authority
from support.gateway_process import ROOT, StartGateway
from support.ports import free_port
from support.psctl import psctl

from clients import AsyncClient, ClientCredentials, GatewayUnreachable, Unavailable

__all__ = ["certificates"]

SIM = """
[[services]]
name = "bot"
type = "sim-robot"
"""


def _tls_config(certs: CertificateFiles, *, mutual: bool) -> str:
    text = f"""
[tls]
cert = "{certs.server.cert}"
key = "{certs.server.key}"
"""
    if mutual:
        text += f'client_ca = "{certs.ca}"\nrequire_client_cert = true\n'
    return text + SIM


def _grpc_credentials(certs: CertificateFiles, client: str | None = "alice") -> grpc.ChannelCredentials:
    pair = certs.clients[client] if client else None
    return grpc.ssl_channel_credentials(
        root_certificates=certs.ca.read_bytes(),
        private_key=pair.key.read_bytes() if pair else None,
        certificate_chain=pair.cert.read_bytes() if pair else None,
    )


async def test_tls_get_with_the_sdk(gateway_process: StartGateway, certificates: CertificateFiles) -> None:
    gw = gateway_process(
        _tls_config(certificates, mutual=False), credentials=_grpc_credentials(certificates, None)
    )
    async with AsyncClient(gw.address, credentials=ClientCredentials(ca=str(certificates.ca))) as client:
        assert await client.get("bot", "location")
    # The same port does not speak plaintext.
    async with AsyncClient(gw.address, timeout=3) as plain:
        with pytest.raises(GatewayUnreachable):
            await plain.get("bot", "location")


async def test_mtls_get_with_the_sdk_and_token_metadata(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    gw = gateway_process(_tls_config(certificates, mutual=True), credentials=_grpc_credentials(certificates))
    alice = certificates.clients["alice"]
    credentials = ClientCredentials(
        ca=str(certificates.ca), cert=str(alice.cert), key=str(alice.key), token="t0k"
    )
    async with AsyncClient(gw.address, credentials=credentials) as client:
        assert client.metadata == (("authorization", "Bearer t0k"),)
        assert await client.get("bot", "location")
        async with client.session() as session:
            assert await session.get("bot", "location")


@pytest.mark.parametrize("who", ["none", "expired", "foreign"])
async def test_mtls_refuses_a_client_without_a_good_certificate(
    gateway_process: StartGateway, certificates: CertificateFiles, who: str
) -> None:
    gw = gateway_process(_tls_config(certificates, mutual=True), credentials=_grpc_credentials(certificates))
    pair = {"none": None, "expired": certificates.expired, "foreign": certificates.foreign}[who]
    credentials = ClientCredentials(
        ca=str(certificates.ca), cert=str(pair.cert) if pair else "", key=str(pair.key) if pair else ""
    )
    async with AsyncClient(gw.address, credentials=credentials, timeout=3) as client:
        with pytest.raises(GatewayUnreachable):
            await client.get("bot", "location")
    # The raw status: the handshake fails, so the call is UNAVAILABLE (docs/errors.md).
    async with grpc.aio.secure_channel(gw.address, credentials.channel_credentials()) as channel:
        call = channel.unary_unary("/grpc.health.v1.Health/Check")
        with pytest.raises(grpc.aio.AioRpcError) as caught:
            await call(b"", timeout=3)
        assert caught.value.code() == grpc.StatusCode.UNAVAILABLE


def test_grpcurl_over_mtls(gateway_process: StartGateway, certificates: CertificateFiles) -> None:
    grpcurl = shutil.which("grpcurl")
    assert grpcurl, "grpcurl is not installed (the [test] extra has it)"
    gw = gateway_process(_tls_config(certificates, mutual=True), credentials=_grpc_credentials(certificates))
    alice = certificates.clients["alice"]
    request = json.dumps({"service": "bot", "property": "location"})
    base = [grpcurl, "-cacert", str(certificates.ca), "-H", "authorization: Bearer t0k"]
    ok = subprocess.run(
        [*base, "-cert", str(alice.cert), "-key", str(alice.key), "-d", request, gw.address,
         "propertyservice.v1.PropertyService/Get"],
        check=False, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert ok.returncode == 0, ok.stderr
    assert "value" in json.loads(ok.stdout)
    refused = subprocess.run(
        [*base, "-d", request, gw.address, "propertyservice.v1.PropertyService/Get"],
        check=False, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert refused.returncode != 0 and not refused.stdout, refused.stdout
    assert "Failed to dial target host" in refused.stderr, refused.stderr


async def test_sighup_reloads_certificates_and_keeps_open_streams(
    gateway_process: StartGateway, certificates: CertificateFiles, tmp_path: Path
) -> None:
    # The config names copies, so the test can replace the files the gateway reads.
    live = tmp_path / "live"
    live.mkdir()
    for name in ("server.pem", "server.key"):
        shutil.copy(certificates.folder / name, live / name)
    config = f"""
[tls]
cert = "{live / "server.pem"}"
key = "{live / "server.key"}"
client_ca = "{certificates.ca}"
require_client_cert = true
{SIM}"""
    gw = gateway_process(config, credentials=_grpc_credentials(certificates))
    alice = certificates.clients["alice"]
    old = ClientCredentials(ca=str(certificates.ca), cert=str(alice.cert), key=str(alice.key))
    async with AsyncClient(gw.address, credentials=old) as client:
        stream = client.listen("bot", "location")
        first = await anext(stream)
        assert first.value
        # A server certificate from a new CA replaces the old one on disk; SIGHUP reads it.
        new_ca = make_authority(tmp_path, "new-ca")
        new_server = issue_certificate(new_ca, tmp_path, "new-server", "localhost", server=True)
        shutil.copy(new_server.cert, live / "server.pem")
        shutil.copy(new_server.key, live / "server.key")
        gw.proc.send_signal(signal.SIGHUP)
        await asyncio.sleep(0.5)
        assert "TLS certificates reloaded" in gw.output
        # A new connection gets the new certificate: trusted through the new CA, not the old.
        fresh = ClientCredentials(ca=str(new_ca.cert_path), cert=str(alice.cert), key=str(alice.key))
        async with AsyncClient(gw.address, credentials=fresh) as again:
            assert await again.get("bot", "location")
            # The stream opened before the reload still delivers: a new connection moves the robot.
            await again.set("bot", "velocity", "(0.5 0 0 0 0 0)")
            second = await asyncio.wait_for(anext(stream), 10)
            assert second.property == "location" and second.value != first.value
        async with AsyncClient(gw.address, credentials=old, timeout=3) as stale:
            with pytest.raises(GatewayUnreachable):
                await stale.get("bot", "location")
        await stream.aclose()
    assert gw.proc.poll() is None


def _check_config(text: str, tmp_path: Path) -> subprocess.CompletedProcess[str]:
    path = tmp_path / "site.toml"
    path.write_text(text)
    return subprocess.run(
        [sys.executable, "-m", "gateway.cli", "check-config", str(path)],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=30,
    )  # fmt: skip


def test_plaintext_on_a_non_loopback_address_is_refused(
    tmp_path: Path, certificates: CertificateFiles
) -> None:
    refused = _check_config('[gateway]\nlisten = "0.0.0.0:50051"\n' + SIM, tmp_path)
    assert refused.returncode == 2
    assert "reachable from other machines and is not encrypted" in refused.stderr
    assert "allow_insecure_remote" in refused.stderr
    line = _check_config('[gateway]\nline_listen = "0.0.0.0:7100"\n' + SIM, tmp_path)
    assert line.returncode == 2 and "[tls.line]" in line.stderr
    allowed = _check_config(
        '[gateway]\nlisten = "0.0.0.0:50051"\nallow_insecure_remote = true\n' + SIM, tmp_path
    )
    assert allowed.returncode == 0, allowed.stderr
    with_tls = _check_config(
        '[gateway]\nlisten = "0.0.0.0:50051"\n' + _tls_config(certificates, mutual=True), tmp_path
    )
    assert with_tls.returncode == 0, with_tls.stderr
    # The --listen override is held to the same rule.
    served = subprocess.run(
        [sys.executable, "-m", "gateway.cli", "serve", "--listen", f"0.0.0.0:{free_port()}"],
        check=False, cwd=ROOT, capture_output=True, text=True, timeout=30,
    )  # fmt: skip
    assert served.returncode == 2
    assert "not encrypted" in served.stderr


async def test_line_listener_over_tls(gateway_process: StartGateway, certificates: CertificateFiles) -> None:
    config = f"""
[gateway]
line_listen = "127.0.0.1:0"
[tls.line]
cert = "{certificates.server.cert}"
key = "{certificates.server.key}"
{SIM}"""
    port = free_port()
    gw = gateway_process(config.replace("127.0.0.1:0", f"127.0.0.1:{port}"))
    context = ssl.create_default_context(cafile=str(certificates.ca))
    reader, writer = await asyncio.open_connection(
        "127.0.0.1", port, ssl=context, server_hostname="localhost"
    )
    hello = await asyncio.wait_for(reader.readline(), 5)
    assert hello.startswith(b"HELLO")
    writer.write(b"GET bot.location\n")
    await writer.drain()
    reply = await asyncio.wait_for(reader.readline(), 5)
    assert reply.startswith(b"OK"), reply
    writer.close()
    # Plaintext on the TLS listener gets no greeting.
    plain_reader, plain_writer = await asyncio.open_connection("127.0.0.1", port)
    plain_writer.write(b"GET bot.location\n")
    await plain_writer.drain()
    assert not (await asyncio.wait_for(plain_reader.read(100), 5)).startswith(b"HELLO")
    plain_writer.close()
    assert gw.proc.poll() is None


async def test_sighup_reloads_the_line_listeners_certificate_and_keeps_open_connections(
    gateway_process: StartGateway, certificates: CertificateFiles, tmp_path: Path
) -> None:
    live = tmp_path / "live"
    live.mkdir()
    for name in ("server.pem", "server.key"):
        shutil.copy(certificates.folder / name, live / name)
    port = free_port()
    gw = gateway_process(f"""
[gateway]
line_listen = "127.0.0.1:{port}"
[tls.line]
cert = "{live / "server.pem"}"
key = "{live / "server.key"}"
{SIM}""")

    async def connect(ca: Path) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
        context = ssl.create_default_context(cafile=str(ca))
        reader, writer = await asyncio.open_connection(
            "127.0.0.1", port, ssl=context, server_hostname="localhost"
        )
        assert (await asyncio.wait_for(reader.readline(), 5)).startswith(b"HELLO")
        return reader, writer

    async def get(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> bytes:
        writer.write(b"GET bot.location\n")
        await writer.drain()
        return await asyncio.wait_for(reader.readline(), 5)

    before = await connect(certificates.ca)
    new_ca = make_authority(tmp_path, "new-ca")
    new_server = issue_certificate(new_ca, tmp_path, "new-server", "localhost", server=True)
    shutil.copy(new_server.cert, live / "server.pem")
    shutil.copy(new_server.key, live / "server.key")
    gw.proc.send_signal(signal.SIGHUP)
    deadline = asyncio.get_running_loop().time() + 5
    while "line listener: TLS certificates reloaded" not in gw.output:
        assert asyncio.get_running_loop().time() < deadline, gw.output
        await asyncio.sleep(0.05)
    # A new connection gets the new certificate: trusted through the new CA, not the old one.
    after = await connect(new_ca.cert_path)
    assert (await get(*after)).startswith(b"OK")
    with pytest.raises(ssl.SSLError):
        await connect(certificates.ca)
    # The connection opened before the reload carries on.
    assert (await get(*before)).startswith(b"OK")
    for _, writer in (before, after):
        writer.close()
    assert gw.proc.poll() is None


async def test_grpcs_federation_between_two_gateway_processes_over_mtls(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    remote = gateway_process(
        _tls_config(certificates, mutual=True), credentials=_grpc_credentials(certificates)
    )
    bob = certificates.clients["bob"]
    local = gateway_process(f"""
[[services]]
name = "far"
url = "grpcs://{remote.address}/bot"
options = {{ ca = "{certificates.ca}", cert = "{bob.cert}", key = "{bob.key}" }}

[[services]]
name = "unknown_ca"
url = "grpcs://{remote.address}/bot"
options = {{ cert = "{bob.cert}", key = "{bob.key}", connect_timeout = 1 }}

[[services]]
name = "no_cert"
url = "grpcs://{remote.address}/bot"
options = {{ ca = "{certificates.ca}", connect_timeout = 1 }}
""")
    async with AsyncClient(local.address, timeout=5) as client:
        assert await client.get("far", "location") == await client.get("far", "location")
        await client.set("far", "velocity", "(0.5 0 0 0 0 0)")
        async with AsyncClient(remote.address, credentials=_sdk_credentials(certificates)) as direct:
            assert await direct.get("bot", "velocity") == "(0.5 0 0 0 0 0)"
        for refused in ("unknown_ca", "no_cert"):
            # The local gateway was reached: its service is unavailable, the remote named.
            with pytest.raises(Unavailable, match=f"bot on gateway {remote.address}") as failed:
                await client.get(refused, "location")
            assert not isinstance(failed.value, GatewayUnreachable)


def _sdk_credentials(certs: CertificateFiles, client: str = "alice") -> ClientCredentials:
    pair = certs.clients[client]
    return ClientCredentials(ca=str(certs.ca), cert=str(pair.cert), key=str(pair.key))


def test_grpcs_options_are_checked(tmp_path: Path, certificates: CertificateFiles) -> None:
    cases = {
        f'url = "grpc://127.0.0.1:1/bot"\noptions = {{ ca = "{certificates.ca}" }}': "need TLS: use grpcs://",
        f'url = "grpcs://127.0.0.1:1/bot"\noptions = {{ cert = "{certificates.server.cert}" }}': "give both",
        'url = "grpcs://127.0.0.1:1/bot"\noptions = { ca = "/no/ca.pem" }': "cannot read '/no/ca.pem'",
    }
    for entry, message in cases.items():
        result = _check_config(f'[[services]]\nname = "far"\n{entry}\n', tmp_path)
        assert result.returncode == 2 and message in result.stderr, result.stderr


def test_psctl_over_mtls_with_flags_and_environment(
    gateway_process: StartGateway, certificates: CertificateFiles, monkeypatch: pytest.MonkeyPatch
) -> None:
    gw = gateway_process(_tls_config(certificates, mutual=True), credentials=_grpc_credentials(certificates))
    alice = certificates.clients["alice"]
    flags = ["--ca", str(certificates.ca), "--cert", str(alice.cert), "--key", str(alice.key), "--token", "t"]
    ok = psctl(gw.address, *flags, "get", "bot", "location")
    assert ok.returncode == 0 and ok.stdout.startswith("("), ok.stderr
    without = psctl(gw.address, "--ca", str(certificates.ca), "--timeout", "3", "get", "bot", "location")
    assert without.returncode == 3, without.stderr
    monkeypatch.setenv("PSCTL_CA", str(certificates.ca))
    monkeypatch.setenv("PSCTL_CERT", str(alice.cert))
    monkeypatch.setenv("PSCTL_KEY", str(alice.key))
    from_env = psctl(gw.address, "get", "bot", "location")
    assert from_env.returncode == 0, from_env.stderr
    missing = psctl(gw.address, "--ca", "/no/ca.pem", "get", "bot", "location")
    assert missing.returncode == 2 and "no such file" in missing.stderr
