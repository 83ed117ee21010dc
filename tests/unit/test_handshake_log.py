"""Failed TLS handshakes in the log: OpenSSL's own errors explained, and the lines bounded per
address and in all, with the rest counted (short intervals stand in for the minute)."""

from __future__ import annotations

import asyncio
import logging
import ssl

import pytest

from gateway.handshake_log import HandshakeFailureLog, TlsPortAdvice, explain_handshake_failure

ADVICE = TlsPortAdvice(connect="use https:// and the CA", requires_cert="[tls] require_client_cert")


def _server_error(first_bytes: bytes) -> ssl.SSLError:
    """The error OpenSSL raises in a server handshake that reads ``first_bytes`` (no socket)."""
    context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    incoming, outgoing = ssl.MemoryBIO(), ssl.MemoryBIO()
    server = context.wrap_bio(incoming, outgoing, server_side=True)
    incoming.write(first_bytes)
    with pytest.raises(ssl.SSLError) as caught:
        server.do_handshake()
    return caught.value


def test_an_http_request_on_a_tls_port_is_called_a_plaintext_client() -> None:
    verdict = explain_handshake_failure(_server_error(b"GET / HTTP/1.1\r\nHost: gw\r\n\r\n"), ADVICE)
    assert verdict is not None
    assert verdict.failed == "HTTP_REQUEST"
    assert verdict.cause == "a plaintext client on the TLS port: use https:// and the CA"


def test_a_line_of_text_on_a_tls_port_is_called_a_plaintext_client() -> None:
    verdict = explain_handshake_failure(_server_error(b"SET bot.velocity (0 0 0)\n"), ADVICE)
    assert verdict is not None and verdict.cause.startswith("a plaintext client on the TLS port")


def test_a_peer_that_leaves_before_tls_begins_is_no_mismatch() -> None:
    assert explain_handshake_failure(ConnectionResetError("gone"), ADVICE) is None


def _lines(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.name == "gateway.handshake_log" and r.levelname == "WARNING"
    ]


async def test_one_address_gets_one_line_per_interval_and_the_rest_is_counted(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, "gateway.handshake_log")
    failures = HandshakeFailureLog("http.listen", ADVICE, interval=0.05, most_lines=10)
    error = _server_error(b"GET / HTTP/1.1\r\n\r\n")
    for _ in range(4):
        failures.failed("10.0.0.7", error)
    assert len(_lines(caplog)) == 1
    await asyncio.sleep(0.1)  # the interval is over: the held-back count is written
    lines = _lines(caplog)
    assert len(lines) == 2
    assert "3 more failed TLS handshake(s)" in lines[1] and "10.0.0.7: HTTP_REQUEST" in lines[1]
    failures.failed("10.0.0.7", error)  # a new interval: the address is named again
    assert len(_lines(caplog)) == 3
    failures.close()
    assert len(_lines(caplog)) == 3  # nothing held back, nothing more written


async def test_many_addresses_get_at_most_the_cap_and_close_writes_the_rest(
    caplog: pytest.LogCaptureFixture,
) -> None:
    caplog.set_level(logging.WARNING, "gateway.handshake_log")
    failures = HandshakeFailureLog("http.listen", ADVICE, interval=60.0, most_lines=3)
    error = _server_error(b"GET / HTTP/1.1\r\n\r\n")
    for n in range(10):
        failures.failed(f"10.0.0.{n}", error)
    assert [line.split(" failed")[0] for line in _lines(caplog)] == [
        f"http.listen: TLS handshake with 10.0.0.{n}" for n in range(3)
    ]
    failures.close()
    assert "7 more failed TLS handshake(s)" in _lines(caplog)[-1]
