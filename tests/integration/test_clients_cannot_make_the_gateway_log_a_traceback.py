"""Nothing a client sends makes a real gateway process log a traceback: crafted tokens on gRPC, HTTP
and the console's cookie, malformed HTTP headers on a raw socket, Session Listens that fail on a
device and on storage, a gRPC Listen cancelled with a large message pending. Each expected failure
is at most one rate-limited line; the process's whole log is checked when the test stops it
(tests/support/gateway_process.py), and each test also counts the lines it provoked."""

from __future__ import annotations

import asyncio
import base64
import json
import sys
import time
from pathlib import Path

import aiohttp
import grpc
import jwt
import pytest
from cryptography.hazmat.primitives.asymmetric import rsa
from scripted_device import ScriptedDevice, tcp_scripted
from support.gateway_process import GatewayProcess, StartGateway

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc
from services.kernel.line_protocol import Listen

SECRET = "correct horse battery staple, long enough for HS256"
WAIT = 20.0
STORAGE = '[[services]]\nname = "files"\ntype = "storage"\noptions = { directory = "store" }\n'
#: Lines of client faults a burst may write before the rate limit holds them back, and the
#: ``suppressed`` line after: how many lines this many faults may cost at most.
BURST_LINES = 40


def b64(data: bytes) -> str:
    return base64.urlsafe_b64encode(data).rstrip(b"=").decode()


def crafted_tokens() -> dict[str, str]:
    """The two tokens that were INTERNAL: ES256 naming an RSA key, and a signed list of non-texts."""
    header = b64(json.dumps({"alg": "ES256", "kid": "rsa"}).encode())
    claims = b64(json.dumps({"sub": "mallory", "exp": int(time.time()) + 3600}).encode())
    numbers = jwt.encode({"sub": "mallory", "exp": int(time.time()) + 3600, "scope": [1, 2]}, SECRET, "HS256")
    return {"es256 naming an rsa key": f"{header}.{claims}.{b64(b'x' * 64)}", "scope of numbers": numbers}


def secured_config(folder: Path) -> str:
    key = rsa.generate_private_key(public_exponent=65537, key_size=2048)
    jwk = json.loads(jwt.algorithms.RSAAlgorithm.to_jwk(key.public_key()))
    (folder / "keys.json").write_text(json.dumps({"keys": [{**jwk, "kid": "rsa"}]}))
    (folder / "jwt.secret").write_text(SECRET)
    return """
        [auth]
        jwt_secret_file = "jwt.secret"
        jwks_file = "keys.json"

        [[services]]
        name = "bot"
        type = "sim-robot"
    """


def lines_since(gw: GatewayProcess, mark: int) -> list[str]:
    return gw.output[mark:].splitlines()


def test_the_log_check_fails_a_gateway_that_logged_a_traceback_unless_the_test_expects_it() -> None:
    program = (
        "import logging, sys\n"
        "logging.basicConfig(format='%(asctime)s %(levelname)s %(name)s: %(message)s')\n"
        "try:\n    {}['crash']\nexcept KeyError:\n    logging.exception('it broke')\n"
        "print('listening on 127.0.0.1:1', flush=True)\n"
    )
    for expected in (False, True):
        gw = GatewayProcess([sys.executable, "-c", program])
        gw.proc.wait(WAIT)
        if expected:
            gw.expect_in_log(r"KeyError: 'crash'")
            gw.stop()
        else:
            with pytest.raises(AssertionError, match="logged 1 unexpected traceback") as caught:
                gw.stop()
            assert "it broke" in str(caught.value) and "KeyError: 'crash'" in str(caught.value)


async def test_crafted_tokens_are_unauthenticated_on_grpc_http_and_the_cookie(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    gw = gateway_process(secured_config(tmp_path))
    url = f"{gw.http_url}api/v1/services/bot/properties/speed"
    async with (
        grpc.aio.insecure_channel(gw.address) as channel,
        aiohttp.ClientSession() as http,
    ):
        stub = pb_grpc.PropertyServiceStub(channel)
        for name, token in crafted_tokens().items():
            with pytest.raises(grpc.aio.AioRpcError) as refused:
                await stub.Get(
                    pb.GetRequest(service="bot", property="speed"),
                    metadata=(("authorization", f"Bearer {token}"),),
                    timeout=WAIT,
                )
            assert refused.value.code() == grpc.StatusCode.UNAUTHENTICATED, (name, refused.value)
            assert "bearer token refused" in (refused.value.details() or "")
            async with http.get(url, headers={"Authorization": f"Bearer {token}"}) as response:
                assert response.status == 401, (name, await response.text())
                assert (await response.json())["error"]["code"] == "UNAUTHENTICATED"
            async with http.get(url, cookies={"ps_token": token}) as response:
                assert response.status == 401, (name, await response.text())
    assert "INTERNAL" not in gw.output
    gw.stop()  # fails the test if the process logged a traceback


async def test_malformed_http_headers_cost_at_most_the_rate_limited_lines(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process()
    host, port = gw.http_address.rsplit(":", 1)
    mark = len(gw.output)
    bad_requests = [
        b"GET /api/v1/health HTTP/1.1\r\nHost: localhost\r\nBad Header\r\n\r\n",
        b"GET /api/v1/health HTTP/1.1\r\nHost: localhost\r\nX: a\x00b\r\n\r\n",
        b"GET /api/v1/health HTTP/1.1\r\nHost: localhost\r\nContent-Length: -5\r\n\r\n",
        b"GET /api/v1/health HTTP/1.1\r\nHost: localhost\r\n" + b"X-Long: " + b"a" * 70_000 + b"\r\n\r\n",
        b"GET /api/v1/health HTTP/9.9\r\nHost: localhost\r\n\r\n",
    ]
    sent = 0
    for _ in range(20):
        for request in bad_requests:
            reader, writer = await asyncio.open_connection(host, int(port))
            writer.write(request)
            await writer.drain()
            answer = await asyncio.wait_for(reader.read(), WAIT)
            writer.close()
            assert answer.startswith((b"HTTP/1.1 4", b"HTTP/1.0 4")), answer[:200]
            sent += 1
    await asyncio.sleep(0.5)  # the last lines reach the pipe
    provoked = lines_since(gw, mark)
    assert len(provoked) <= BURST_LINES, "\n".join(provoked[:50])
    assert any("Error handling request from 127.0.0.1: BadHttpMessage" in line for line in provoked), provoked
    gw.stop()


class RefusesListen(ScriptedDevice):
    """A line device that answers every LISTEN with an error (a sensor that cannot stream)."""

    def _answer(self, frame):  # type: ignore[no-untyped-def]
        if isinstance(frame, Listen):
            tag = getattr(frame, "tag", None)
            return f"{'#' + str(tag) + ' ' if tag else ''}ERR 12 cannot stream {frame.path}"
        return super()._answer(frame)


async def session_listens(address: str, requests: list[pb.Request]) -> list[pb.Reply]:
    """Send ``requests`` in one Session message; the replies, once every one has its answer."""
    async with grpc.aio.insecure_channel(address) as channel:
        call = pb_grpc.PropertyServiceStub(channel).Session()
        await call.write(pb.SessionRequest(requests=requests))
        replies: list[pb.Reply] = []
        while len(replies) < len(requests):
            message = await asyncio.wait_for(call.read(), WAIT)
            assert message is not grpc.aio.EOF
            replies.extend(message.replies)
        await call.done_writing()
        call.cancel()
    return replies


async def test_session_listens_that_fail_on_a_device_are_answered_without_a_traceback(
    gateway_process: StartGateway,
) -> None:
    device = RefusesListen("HELLO 1 name=therm type=sensor push=1", {"a": "1", "b": "2"})
    async with tcp_scripted(device) as url:
        gw = gateway_process(f'[[services]]\nname = "therm"\nurl = "{url}"\n')
        mark = len(gw.output)
        n = 300
        listens = [
            pb.Request(id=i, listen=pb.ListenRequest(service="therm", property="a" if i % 2 else "b"))
            for i in range(n)
        ]
        replies = await session_listens(gw.address, listens)
        failed = [reply for reply in replies if reply.status.code != 0]
        assert len(failed) == n and all("cannot stream" in reply.status.message for reply in failed)
        await asyncio.sleep(0.5)
        provoked = lines_since(gw, mark)
        assert len(provoked) <= BURST_LINES, "\n".join(provoked[:50])
        gw.stop()


async def test_session_listens_that_fail_on_storage_are_answered_without_a_traceback(
    gateway_process: StartGateway, tmp_path: Path
) -> None:
    gw = gateway_process(STORAGE)
    (tmp_path / "store" / "a-folder").mkdir(parents=True)
    (tmp_path / "store" / "latin1.txt").write_bytes(b"caf\xe9\n")
    mark = len(gw.output)
    names = ["a-folder", "latin1.txt", "../outside", "missing.txt"]
    listens = [
        pb.Request(
            id=i,
            listen=pb.ListenRequest(service="files", property="file", parameters={"name": names[i % 4]}),
        )
        for i in range(200)
    ]
    replies = await session_listens(gw.address, listens)
    answered = {reply.id for reply in replies}
    assert answered == set(range(200))
    await asyncio.sleep(0.5)
    provoked = lines_since(gw, mark)
    assert len(provoked) <= BURST_LINES, "\n".join(provoked[:50])
    gw.stop()


async def test_a_grpc_listen_cancelled_with_a_large_message_pending_costs_one_line(
    gateway_process: StartGateway,
) -> None:
    gw = gateway_process(STORAGE)
    name = {"name": "big.bin"}
    mark = len(gw.output)
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)

        async def store(fill: int) -> None:
            data = bytes([fill]) * 3_000_000
            request = pb.SetRequest(service="files", property="blob", parameters=name, data=data)
            await stub.Set(request, timeout=WAIT)

        await store(0)
        for _ in range(3):
            # A reader that takes nothing: the value waits in the server's send, more come behind
            # it, and the call is cancelled under them.
            call = stub.Listen(pb.ListenRequest(service="files", property="blob", parameters=name))
            for fill in range(1, 4):
                await asyncio.sleep(0.3)
                await store(fill)
            call.cancel()
            await asyncio.sleep(0.3)
    await asyncio.sleep(0.5)
    provoked = lines_since(gw, mark)
    assert len(provoked) <= BURST_LINES, "\n".join(provoked[:50])
    went_away = [line for line in provoked if "went away while a message was being sent" in line]
    assert went_away, "\n".join(provoked)  # the case happened, and cost its one line
    gw.stop()
