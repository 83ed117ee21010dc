"""The HTTP/JSON routes of a real gateway process, used as a browser or curl would use them.

Every call goes through the gateway's one call layer, so what a Set over HTTP changes a gRPC
Get reads, and the answers and errors are those of the gRPC port, as JSON.
"""

from __future__ import annotations

from collections.abc import AsyncIterator, Iterator
from typing import Any

import aiohttp
import pytest
from support.board import BOARD_TYPE
from support.gateway_process import GatewayProcess, start_gateway

from clients import AsyncClient

CONFIG = f"""
[[services]]
name = "board"
type = "{BOARD_TYPE}"

[[services]]
name = "scout1"
type = "sim-robot"

[[services]]
name = "thermo1"
type = "sim-sensor"
options = {{ location = [2.0, 3.0] }}
"""

JSON = {"Content-Type": "application/json"}


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("http"), CONFIG)
    yield gw
    gw.stop()


@pytest.fixture
async def http(gateway: GatewayProcess) -> AsyncIterator[aiohttp.ClientSession]:
    async with aiohttp.ClientSession(base_url=gateway.http_url) as session:
        yield session


@pytest.fixture
async def grpc_client(gateway: GatewayProcess) -> AsyncIterator[AsyncClient]:
    async with AsyncClient(gateway.address, timeout=10) as client:
        yield client


async def call(
    http: aiohttp.ClientSession, method: str, url: str, **kwargs: Any
) -> tuple[int, Any, aiohttp.ClientResponse]:
    async with http.request(method, url, **kwargs) as response:
        return response.status, await response.json(), response


def prop(service: str, path: str) -> str:
    return f"/api/v1/services/{service}/properties/{path}"


async def test_health_answers_ok(http: aiohttp.ClientSession) -> None:
    status, body, response = await call(http, "GET", "/api/v1/health")
    assert (status, body) == (200, {"status": "ok"})
    assert response.headers["Content-Type"].startswith("application/json")
    assert "Access-Control-Allow-Origin" not in response.headers  # no CORS, ever


async def test_services_lists_what_the_registry_knows(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    status, body, _ = await call(http, "GET", "/api/v1/services")
    assert status == 200
    rows = {row["name"]: row for row in body["services"]}
    assert [row["name"] for row in body["services"]] == await grpc_client.services()
    assert rows["board"] == {
        "name": "board",
        "type": "board",
        "state": "up",
        "address": "local",
        "location": None,
    }
    assert rows["thermo1"]["type"] == "sensor"
    assert rows["thermo1"]["location"] == [2.0, 3.0, 0.0, 0.0, 0.0, 0.0]
    assert rows["scout1"]["type"] == "mobile_robot" and rows["scout1"]["state"] == "up"
    assert rows["registry"]["type"] == "registry"


async def test_model_is_the_describe_model(http: aiohttp.ClientSession, grpc_client: AsyncClient) -> None:
    status, body, _ = await call(http, "GET", "/api/v1/services/board/model")
    assert status == 200
    assert (body["service"], body["type"]) == ("board", "board")
    described = await grpc_client.describe("board")
    assert [p["name"] for p in body["properties"]] == [p.name for p in described.properties]
    level = next(p for p in body["properties"] if p["name"] == "level")
    assert level == {
        "name": "level",
        "type": "number",
        "access": "read-write",
        "unit": "m",
        "minimum": 0.0,
        "maximum": 10.0,
        "choices": None,
        "length": None,
        "gui": "number",
        "doc": None,
        "value": None,
        "parameters": [],
    }
    ring = next(p for p in body["properties"] if p["name"] == "ring")
    assert ring["access"] == "action"
    assert ring["value"]["type"] == "integer"
    assert ring["parameters"] == [
        {"name": "tone", "type": "text", "required": False, "default": "low", "doc": None}
    ]


async def test_get_reads_what_grpc_reads(http: aiohttp.ClientSession, grpc_client: AsyncClient) -> None:
    status, body, _ = await call(http, "GET", prop("thermo1", "location"))
    assert status == 200
    assert body == {
        "service": "thermo1",
        "path": "location",
        "value": await grpc_client.get("thermo1", "location"),
    }


async def test_a_wildcard_get_lists_every_match(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    status, body, _ = await call(http, "GET", prop("board", "*"))
    assert status == 200
    assert body["service"] == "board" and body["path"] == "*"
    assert {v["path"]: v["value"] for v in body["values"]} == await grpc_client.get_matching("board", "*")
    assert "ring" not in [v["path"] for v in body["values"]]  # an action is never read


async def test_query_string_carries_request_parameters(http: aiohttp.ClientSession) -> None:
    status, body, _ = await call(http, "GET", prop("registry", "find"), params={"type": "sensor"})
    assert status == 200
    assert body["value"] == "(thermo1)"


async def test_set_over_http_is_what_a_grpc_get_reads(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    status, body, _ = await call(http, "PUT", prop("board", "note"), json={"value": "hello, 世界"})
    assert status == 200
    assert body == {"service": "board", "path": "note", "value": "hello, 世界"}
    assert await grpc_client.get("board", "note") == "hello, 世界"


@pytest.mark.parametrize(
    ("path", "value", "text"),
    [
        ("level", 1.5, "1.5"),
        ("level", 2, "2"),
        ("level", "2.5", "2.5"),
        ("lit", True, "true"),
        ("point", [1, 2.5], "(1 2.5)"),
        ("point", "(3 4)", "(3 4)"),
    ],
)
async def test_json_values_are_formatted_into_the_value_grammar(
    http: aiohttp.ClientSession, grpc_client: AsyncClient, path: str, value: Any, text: str
) -> None:
    status, body, _ = await call(http, "POST", prop("board", path), json={"value": value})
    assert status == 200, body
    assert await grpc_client.get("board", path) == text


async def test_an_action_takes_its_value_and_parameters(http: aiohttp.ClientSession) -> None:
    body = {"value": 3, "parameters": {"tone": "high"}}
    status, answer, _ = await call(http, "POST", prop("board", "ring"), json=body)
    assert (status, answer["value"]) == (200, "rang 3 times, high")


async def test_a_grpc_set_is_what_an_http_get_reads(
    http: aiohttp.ClientSession, grpc_client: AsyncClient
) -> None:
    await grpc_client.set("board", "note", "from gRPC")
    status, body, _ = await call(http, "GET", prop("board", "note"))
    assert (status, body["value"]) == (200, "from gRPC")


@pytest.mark.parametrize(
    ("method", "url", "body", "expected"),
    [
        ("GET", prop("nosuch", "location"), None, (404, "NOT_FOUND")),
        ("GET", prop("board", "nosuch"), None, (404, "NOT_FOUND")),
        ("GET", prop("board", "ring"), None, (400, "FAILED_PRECONDITION")),  # reads never act
        ("GET", prop("*", "location"), None, (400, "INVALID_ARGUMENT")),
        ("GET", prop("board", "bad..path"), None, (400, "INVALID_ARGUMENT")),
        ("GET", "/api/v1/services/nosuch/model", None, (404, "NOT_FOUND")),
        ("PUT", prop("thermo1", "location"), {"value": "(1 2)"}, (400, "FAILED_PRECONDITION")),
        ("PUT", prop("board", "level"), {"value": 11}, (400, "INVALID_ARGUMENT")),  # above maximum
        ("PUT", prop("board", "lit"), {"value": "perhaps"}, (400, "INVALID_ARGUMENT")),
        (
            "PUT",
            prop("board", "note"),
            {"value": "x", "parameters": {"frame": "robot"}},
            400,
            "INVALID_ARGUMENT",
        ),
        ("PUT", prop("registry", "services.scout1"), {"value": "tcp://127.0.0.1:1"}, (409, "ALREADY_EXISTS")),
    ],
)
async def test_errors_are_json_with_the_grpc_code_and_its_http_status(
    http: aiohttp.ClientSession, method: str, url: str, body: Any, expected: tuple[int, str]
) -> None:
    got, answer, response = await call(http, method, url, json=body)
    assert (got, answer["error"]["code"]) == expected, answer
    assert answer["error"]["message"]
    assert response.headers["Content-Type"].startswith("application/json")


async def test_the_openapi_document_lists_the_routes(http: aiohttp.ClientSession) -> None:
    status, doc, _ = await call(http, "GET", "/api/v1/openapi.json")
    assert status == 200
    assert doc["openapi"].startswith("3.1")
    assert set(doc["paths"]["/api/v1/services/{service}/properties/{path}"]) == {"get", "put", "post"}
    assert "/api/v1/events" in doc["paths"]


async def test_the_console_is_served_at_the_root(http: aiohttp.ClientSession) -> None:
    async with http.get("/") as root, http.get("/console/index.html") as same:
        assert root.status == 200 and same.status == 200
        assert root.headers["Content-Type"] == "text/html; charset=utf-8"
        assert root.headers["Cache-Control"] == "no-cache"
        assert await root.text() == await same.text()
        assert "<html" in (await root.text()).lower()
