"""JSON log lines and request ids, through a real gateway process and a device process on TCP.

A client names its call with ``x-request-id`` (or gets an id); the id comes back to it, and every
log line of the call carries it: the gateway's own, and the TCP proxy's line of what it sent to the
device, with the line protocol's tag beside it.
"""

from __future__ import annotations

import json
from typing import Any

import aiohttp
import grpc
import pytest
from line_device_support import device_process, tcp_device
from support.gateway_process import GatewayProcess, StartGateway
from support.session_stream import replies_until
from support.waiting import wait_until

from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

#: Lines the gateway prints whatever the log format: scripts read its ports there.
PRINTED = ("listening on ", "HTTP front end and console on ")


def config(port: int, log_format: str = "json") -> str:
    return f"""
        [gateway]
        log_format = "{log_format}"
        log_level = "debug"

        [[services]]
        name = "rover"
        url = "tcp://127.0.0.1:{port}"
    """


def log_lines(gw: GatewayProcess) -> list[dict[str, Any]]:
    """Every log line of the gateway, each parsed; a line that is not one JSON object fails the test."""
    parsed = []
    for line in gw.output.splitlines():
        if line.startswith(PRINTED):
            continue
        entry = json.loads(line)
        assert isinstance(entry, dict), line
        parsed.append(entry)
    return parsed


def with_id(gw: GatewayProcess, request_id: str) -> list[dict[str, Any]]:
    return [e for e in log_lines(gw) if e.get("request_id") == request_id]


@pytest.fixture
def rover() -> Any:
    with tcp_device("--service", "sim-robot", "--name", "rover") as (_, port):
        yield port


async def test_every_log_line_is_one_json_object_with_the_fields(
    gateway_process: StartGateway, rover: int
) -> None:
    gw = gateway_process(config(rover))
    entries = log_lines(gw)
    assert entries, gw.output
    for entry in entries:
        assert {"time", "level", "logger", "message"} <= entry.keys(), entry
        assert entry["time"].endswith("Z") and "T" in entry["time"]
        assert entry["level"] in ("debug", "info", "warning", "error", "critical")
    started = [e for e in entries if e["message"].startswith("service rover started")]
    assert started and started[0]["service"] == "rover"


async def test_a_devices_connection_lines_name_its_service(gateway_process: StartGateway) -> None:
    # The proxy's own lines (connecting, connected, disconnected) belong to no request, but to
    # one service: `select(.service == "rover")` finds them.
    args = ("--service", "sim-robot", "--name", "rover", "--tcp", "127.0.0.1:0")
    with device_process(*args) as (device, first):
        gw = gateway_process(config(int(first.rpartition(":")[2])))

        def lines_with(text: str) -> list[dict[str, Any]]:
            return [e for e in log_lines(gw) if text in e["message"]]

        await wait_until(lambda: bool(lines_with(": connected (rover")), what="the connected line")
        device.terminate()
        await wait_until(lambda: bool(lines_with(": disconnected (")), what="the disconnected line")
    for entry in lines_with(": connected (rover") + lines_with(": disconnected ("):
        assert entry["logger"].startswith("gateway.proxies"), entry
        assert entry["service"] == "rover", entry
        assert "request_id" not in entry, entry


async def test_a_session_request_id_ties_its_log_lines_and_the_proxy_line(
    gateway_process: StartGateway, rover: int
) -> None:
    gw = gateway_process(config(rover))
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Session(metadata=(("x-request-id", "mission-7"),))
        assert ("x-request-id", "mission-7") in tuple(await call.initial_metadata())
        await call.write(
            pb.SessionRequest(
                requests=[
                    pb.Request(id=1, get=pb.GetRequest(service="rover", property="location")),
                    pb.Request(id=2, set=pb.SetRequest(service="rover", property="speed", value="0.5")),
                    pb.Request(id=3, get=pb.GetRequest(service="rover", property="nosuch")),
                ]
            )
        )
        replies = await replies_until(call, lambda r: len(r) >= 3)
        await call.done_writing()
    by_id = {r.id: r for r in replies}
    assert by_id[1].get.value == "(0 0 0 0 0 0)"
    assert by_id[3].status.code == grpc.StatusCode.NOT_FOUND.value[0]

    def sent(request_id: str, line: str) -> list[dict[str, Any]]:
        return [e for e in with_id(gw, request_id) if "sent b'#" in e["message"] and line in e["message"]]

    await wait_until(lambda: bool(sent("mission-7/3", "GET nosuch")), what="the proxy's line of request 3")
    get = sent("mission-7/1", "GET location")
    assert len(get) == 1, with_id(gw, "mission-7/1")
    assert get[0]["logger"] == "gateway.proxies.connection"
    assert (get[0]["service"], get[0]["property"]) == ("rover", "location")
    # The tag on the line to the device, as the device's reply carries it back.
    assert " as tag " in get[0]["message"]
    assert sent("mission-7/2", "SET speed 0.5")
    failed = [e for e in with_id(gw, "mission-7/3") if e.get("code") == "NOT_FOUND"]
    assert failed and failed[0]["property"] == "nosuch"


async def test_a_unary_call_gets_an_id_or_keeps_the_clients(
    gateway_process: StartGateway, rover: int
) -> None:
    gw = gateway_process(config(rover))
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        call = stub.Get(
            pb.GetRequest(service="rover", property="location"), metadata=(("x-request-id", "look-1"),)
        )
        await call
        assert ("x-request-id", "look-1") in tuple(await call.trailing_metadata())

        call = stub.Get(pb.GetRequest(service="rover", property="nosuch"))
        with pytest.raises(grpc.aio.AioRpcError) as failed:
            await call
        assert failed.value.code() == grpc.StatusCode.NOT_FOUND
        chosen = dict(failed.value.trailing_metadata() or ())["x-request-id"]
        assert len(chosen) == 16 and int(chosen, 16) >= 0

        # Too long to copy into every log line: a fresh id instead.
        call = stub.Get(
            pb.GetRequest(service="rover", property="location"), metadata=(("x-request-id", "x" * 65),)
        )
        await call
        assert dict(await call.trailing_metadata())["x-request-id"] != "x" * 65

    await wait_until(lambda: bool(with_id(gw, chosen)), what="the failed Get's log line")
    lines = with_id(gw, chosen)
    assert any(e.get("code") == "NOT_FOUND" and e["service"] == "rover" for e in lines), lines
    assert any("GET location" in e["message"] for e in with_id(gw, "look-1"))


async def test_an_http_request_id_is_echoed_and_logged(gateway_process: StartGateway, rover: int) -> None:
    gw = gateway_process(config(rover))
    url = f"{gw.http_url}api/v1/services/rover/properties/location"
    async with (
        aiohttp.ClientSession() as http,
        http.get(url, headers={"X-Request-Id": "from-the-browser"}) as answer,
    ):
        assert answer.status == 200
        assert answer.headers["X-Request-Id"] == "from-the-browser"
    await wait_until(lambda: bool(with_id(gw, "from-the-browser")), what="the HTTP request's proxy line")
    assert any("GET location" in e["message"] for e in with_id(gw, "from-the-browser"))
    async with (
        aiohttp.ClientSession() as http,
        http.get(url.replace("/rover/", "/rover9/"), headers={"X-Request-Id": "web-2"}) as answer,
    ):
        assert answer.status == 404
    await wait_until(lambda: bool(with_id(gw, "web-2")), what="the failed HTTP call's line")
    failed = with_id(gw, "web-2")[0]
    assert (failed["level"], failed["code"], failed["service"]) == ("debug", "NOT_FOUND", "rover9"), failed


async def test_text_lines_name_the_request_too(gateway_process: StartGateway, rover: int) -> None:
    gw = gateway_process(config(rover, "text"))
    async with grpc.aio.insecure_channel(gw.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        await stub.Get(
            pb.GetRequest(service="rover", property="location"), metadata=(("x-request-id", "t-1"),)
        )
    await wait_until(lambda: "[request t-1]" in gw.output, what="a text line naming the request")
    line = next(x for x in gw.output.splitlines() if "[request t-1]" in x)
    assert " DEBUG gateway.proxies.connection: device rover" in line and "GET location" in line


def test_a_bad_log_format_is_a_config_error(gateway_process: StartGateway) -> None:
    with pytest.raises(RuntimeError, match=r"log_format: expected one of text, json, got 'xml'"):
        gateway_process('[gateway]\nlog_format = "xml"\n')


async def test_a_request_id_goes_on_to_the_next_gateway(gateway_process: StartGateway) -> None:
    far = gateway_process(
        '[gateway]\nlog_format = "json"\nlog_level = "debug"\n'
        '[[services]]\nname = "scout"\ntype = "sim-robot"\n'
    )
    near = gateway_process(f'[[services]]\nname = "remote"\nurl = "grpc://{far.address}/scout"\n')
    async with grpc.aio.insecure_channel(near.address) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.aio.AioRpcError) as failed:
            await stub.Get(
                pb.GetRequest(service="remote", property="nosuch"), metadata=(("x-request-id", "fed-1"),)
            )
        assert failed.value.code() == grpc.StatusCode.NOT_FOUND
    # The far gateway logs the forwarded call under the id the client chose at the near one.
    await wait_until(lambda: bool(with_id(far, "fed-1")), what="the far gateway's line of the call")
    line = with_id(far, "fed-1")[0]
    assert (line["service"], line["property"], line["code"]) == ("scout", "nosuch", "NOT_FOUND")
