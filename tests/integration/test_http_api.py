"""The HTTP/JSON routes of a real gateway process, used as a browser or curl would use them.

Every call goes through the gateway's one call layer, so what a Set over HTTP changes a gRPC
Get reads, and the answers and errors are those of the gRPC port, as JSON.
"""

from __future__ import annotations

import json
import re
import shlex
import shutil
import ssl
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import aiohttp
import grpc
import jwt
import pytest
from support.board import BOARD_TYPE
from support.certs import CertificateFiles, certificates
from support.gateway_process import ROOT, GatewayProcess, StartGateway, start_gateway
from support.http_clients import grpc_client, http
from support.sse import SseReader
from support.waiting import eventually

from clients import AsyncClient

__all__ = ["certificates", "grpc_client", "http"]

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

    # The registry follows a service's location from the first time it is read (on demand).
    async def thermo1_location() -> object:
        _, later, _ = await call(http, "GET", "/api/v1/services")
        return {row["name"]: row for row in later["services"]}["thermo1"]["location"]

    location = await eventually(thermo1_location, lambda loc: loc is not None, what="thermo1's location")
    assert location == [2.0, 3.0, 0.0, 0.0, 0.0, 0.0]
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
        "media_type": None,
        "max_size": None,
        "resolution": 0.01,
        "value": None,
        "parameters": [],
    }
    assert next(p for p in described.properties if p.name == "level").resolution == 0.01
    ring = next(p for p in body["properties"] if p["name"] == "ring")
    assert ring["access"] == "action"
    assert ring["value"]["type"] == "integer"
    assert ring["parameters"] == [
        {"name": "tone", "type": "text", "required": False, "default": "low", "doc": None}
    ]


async def test_get_reads_what_grpc_reads(http: aiohttp.ClientSession, grpc_client: AsyncClient) -> None:
    status, body, _ = await call(http, "GET", prop("thermo1", "location"))
    assert status == 200
    reading = await grpc_client.get_with_time("thermo1", "location")
    assert body == {"service": "thermo1", "path": "location", "value": reading.value, "time": body["time"]}
    # The value's source time, in seconds since the epoch as gRPC's Timestamp says it.
    assert abs(body["time"] - reading.time.timestamp()) < 5


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
            (400, "INVALID_ARGUMENT"),
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


# -- identity and rules: the gRPC port's, on every HTTP route ----------------------------------

SECRET = "a shared secret of the lab, long enough for HS256"
RULES = """
[auth]
jwt_secret_file = "jwt.secret"
issuer = "lab"

[[services]]
name = "scout1"
type = "sim-robot"

[[rules]]
subject = "*"
service = "scout1"
operations = ["read"]
effect = "permit"

[[rules]]
subject = "*"
service = "scout1"
path = "sensors.**"
operations = ["read"]
effect = "deny"

[[rules]]
subject = "operator"
service = "scout1"
operations = ["write", "invoke"]
effect = "permit"

[[rules]]
subject = "admin"
operations = ["read", "write", "invoke", "register", "unregister", "admin"]
effect = "permit"
"""


def token(subject: str) -> str:
    claims = {"sub": subject, "iss": "lab", "exp": int(time.time()) + 600}
    return jwt.encode(claims, SECRET, algorithm="HS256")


@pytest.fixture
def secured(gateway_process: StartGateway, tmp_path: Path) -> GatewayProcess:
    (tmp_path / "jwt.secret").write_text(SECRET)
    return gateway_process(RULES)


def bearer(subject: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token(subject)}"}


@pytest.mark.parametrize(
    ("who", "method", "url", "status"),
    [
        (None, "GET", prop("scout1", "location"), 200),
        (None, "GET", prop("scout1", "sensors.bumper"), 401),  # refused, and no credentials given
        ("guest", "GET", prop("scout1", "sensors.bumper"), 403),  # deny beats the broader permit
        (None, "GET", "/api/v1/services/scout1/model", 200),
        ("guest", "GET", "/api/v1/services", 403),  # the registry: nobody but admin reads it
        ("admin", "GET", "/api/v1/services", 200),
        (None, "PUT", prop("scout1", "speed"), 401),
        ("operator", "PUT", prop("scout1", "speed"), 200),
        ("guest", "PUT", prop("scout1", "speed"), 403),
        ("bad", "PUT", prop("scout1", "speed"), 401),
        ("guest", "GET", "/api/v1/events?sel=scout1/sensors.bumper", 403),
        ("cookie:operator", "PUT", prop("scout1", "speed"), 200),
        ("cookie:bad", "GET", prop("scout1", "location"), 401),
    ],
)
async def test_tokens_and_rules_decide_as_on_the_grpc_port(
    secured: GatewayProcess, who: str | None, method: str, url: str, status: int
) -> None:
    headers = {"Content-Type": "application/json"}
    cookies = {}
    if who == "bad":
        headers["Authorization"] = "Bearer not-a-token"
    elif who == "cookie:bad":
        cookies["ps_token"] = "not-a-token"
    elif who is not None and who.startswith("cookie:"):
        cookies["ps_token"] = token(who.partition(":")[2])
    elif who is not None:
        headers.update(bearer(who))
    body = {"value": 0.4} if method == "PUT" else None
    async with (
        aiohttp.ClientSession(base_url=secured.http_url, cookies=cookies) as http,
        http.request(method, url, json=body, headers=headers) as response,
    ):
        assert response.status == status, await response.text()
        if status >= 400:
            error = (await response.json())["error"]
            assert error["code"] == {401: "UNAUTHENTICATED", 403: "PERMISSION_DENIED"}[status]


async def test_an_event_stream_skips_what_its_subject_may_not_read(secured: GatewayProcess) -> None:
    async with (
        aiohttp.ClientSession(base_url=secured.http_url) as http,
        http.get("/api/v1/events", params={"sel": "scout1/*"}) as response,
    ):
        assert response.status == 200
        snapshot = await SseReader(response).values_until_sync()
    paths = [m.data["path"] for m in snapshot]
    assert "location" in paths
    assert not [p for p in paths if p.startswith("sensors.")]


# -- HTTPS: the [tls] certificate, and client certificates naming the caller -------------------------


async def test_https_names_the_caller_by_its_client_certificate(
    gateway_process: StartGateway, certificates: CertificateFiles
) -> None:
    config = f"""
        [tls]
        cert = "{certificates.server.cert}"
        key = "{certificates.server.key}"
        client_ca = "{certificates.ca}"

        [http]
        tls = true

        [[services]]
        name = "scout1"
        type = "sim-robot"

        [[rules]]
        subject = "alice"
        service = "scout1"
        operations = ["read"]
        effect = "permit"
        """
    grpc_credentials = grpc.ssl_channel_credentials(root_certificates=certificates.ca.read_bytes())
    gw = gateway_process(config, credentials=grpc_credentials)
    assert gw.http_url.startswith("https://")
    url = gw.http_url + "api/v1/services/scout1/properties/location"

    def context(client: str | None) -> ssl.SSLContext:
        made = ssl.create_default_context(cafile=str(certificates.ca))
        if client is not None:
            pair = certificates.clients[client]
            made.load_cert_chain(str(pair.cert), str(pair.key))
        return made

    for client, status in (("alice", 200), ("bob", 403), (None, 401)):
        async with aiohttp.ClientSession() as http, http.get(url, ssl=context(client)) as response:
            assert response.status == status, (client, await response.text())
    async with aiohttp.ClientSession() as http:
        with pytest.raises(aiohttp.ClientError):
            await http.get(url.replace("https://", "http://"))


# -- the curl examples of docs/http-api.md, as written ---------------------------------------------

DOC = (ROOT / "docs" / "http-api.md").read_text(encoding="utf-8")


def doc_curl_commands() -> list[list[str]]:
    """The curl lines of the doc's first bash block (continuations joined)."""
    block = DOC.split("```bash", 1)[1].split("```", 1)[0].replace("\\\n", " ")
    lines = [re.sub(r"\s+#.*$", "", line).strip() for line in block.splitlines()]
    return [shlex.split(line) for line in lines if line.startswith("curl ")]


@pytest.mark.skipif(shutil.which("curl") is None, reason="curl is not installed")
def test_the_curl_examples_of_the_doc_work(demo_gateway: GatewayProcess) -> None:
    commands = doc_curl_commands()
    assert len(commands) >= 8
    for command in commands:
        args = [arg.replace("localhost:8080", demo_gateway.http_address) for arg in command]
        streaming = "-sN" in args
        if streaming:  # an event stream does not end by itself: read it for a while
            args[1:1] = ["--max-time", "3"]
        done = subprocess.run(args, capture_output=True, text=True, timeout=30, check=False)
        if streaming:
            assert done.returncode == 28, done.stderr  # curl's "timed out", after reading
            assert "event: sync" in done.stdout and "event: value" in done.stdout
            continue
        assert done.returncode == 0, (command, done.stderr)
        answer = json.loads(done.stdout)
        assert "error" not in answer, (command, answer)
