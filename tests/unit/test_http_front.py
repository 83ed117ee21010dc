"""The HTTP front end's parts that need no gateway: the [http] config section, the OpenAPI document
against the routes the application serves, the console's file rules (served by aiohttp on a real
loopback socket), the error status table and request bodies."""

from __future__ import annotations

import os
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Annotated

import aiohttp
import pytest
from aiohttp import web
from aiohttp.test_utils import TestServer
from support.board import Board

from gateway.app import Gateway
from gateway.config import Config, ConfigError, HttpSection, default_config, loads_config
from gateway.fronts.http import HttpFront
from gateway.fronts.http.binary import served_type
from gateway.fronts.http.bodies import parse_set_body
from gateway.fronts.http.console import Console, console_file
from gateway.fronts.http.errors import HTTP_STATUS
from gateway.fronts.http.openapi import document
from gateway.fronts.http.safety import is_loopback_host
from gateway.testing import running_gateway
from services.kernel.core import Prop, Resource
from services.kernel.errors import Code, InvalidArgument, NotFound

# -- configuration ---------------------------------------------------------------------------


def test_http_is_off_unless_configured_and_the_demo_serves_it() -> None:
    assert loads_config("").http.listen == ""
    demo = default_config()
    assert demo.http.listen == "127.0.0.1:8080"
    http = demo.http
    assert (http.console, http.max_body, http.max_streams, http.max_streams_per_client, http.heartbeat) == (
        True,
        1024 * 1024,
        4096,
        64,
        15.0,
    )
    assert http.write_timeout == 30.0


def test_the_http_section_reads_back() -> None:
    cfg = loads_config(
        '[http]\nlisten = "127.0.0.1:0"\nconsole = false\nmax_body = 1000\nmax_streams = 3\nheartbeat = 0.5\n'
    )
    assert (
        cfg.http.listen,
        cfg.http.console,
        cfg.http.max_body,
        cfg.http.max_streams,
        cfg.http.heartbeat,
    ) == (
        "127.0.0.1:0",
        False,
        1000,
        3,
        0.5,
    )


@pytest.mark.parametrize(
    ("text", "named"),
    [
        ('listen = "8080"', "http.listen: expected host:port"),
        ("max_body = 0", "http.max_body: must be at least 1"),
        ("max_streams = -1", "http.max_streams: must be at least 1, got -1"),
        ("heartbeat = 0", "http.heartbeat"),
        ('heartbeat = "often"', "http.heartbeat: expected a number"),
        ("max_streams_per_client = 0", "http.max_streams_per_client: must be at least 1"),
        ("write_timeout = 0", "http.write_timeout: must be a positive number of seconds"),
        ("write_timeout = nan", "http.write_timeout: must be a positive number of seconds"),
        ("tls = true", "http.tls: HTTPS needs the [tls] section's cert and key"),
        ("colour = 1", "http.colour: unknown key"),
        ('listen = "0.0.0.0:8080"', "is reachable from other machines and is not encrypted"),
    ],
)
def test_a_bad_http_section_names_the_key(text: str, named: str) -> None:
    with pytest.raises(ConfigError) as err:
        loads_config(f"[http]\n{text}\n", "site.toml")
    assert named in str(err.value)


def test_the_command_line_overrides_http_listen() -> None:
    demo = default_config()
    assert demo.with_overrides(http="127.0.0.1:0").http.listen == "127.0.0.1:0"
    assert demo.with_overrides(http="").http.listen == ""
    with pytest.raises(ConfigError, match="--http"):
        demo.with_overrides(http="nowhere")
    with pytest.raises(ConfigError, match="not encrypted"):
        demo.with_overrides(http="0.0.0.0:8080")


# -- routes and the OpenAPI document -----------------------------------------------------------


def served_routes(console: bool) -> set[tuple[str, str]]:
    config = loads_config(f'[http]\nlisten = "127.0.0.1:0"\nconsole = {str(console).lower()}\n')
    gateway = Gateway(config)
    front = HttpFront(gateway.servicer.calls, gateway.hub, config, gateway.guard)
    app = front.build_app()
    return {
        (route.method.lower(), route.resource.canonical)
        for route in app.router.routes()
        if route.resource is not None
    }


@pytest.mark.parametrize("console", [True, False])
def test_every_route_served_is_documented_and_nothing_else(console: bool) -> None:
    documented = {(method, path) for path, item in document(console)["paths"].items() for method in item}
    assert served_routes(console) == documented


def test_the_document_is_openapi_3_1_and_its_references_resolve() -> None:
    doc = document(True)
    assert doc["openapi"] == "3.1.0"
    refs: list[str] = []

    def walk(node: object) -> None:
        if isinstance(node, dict):
            if "$ref" in node:
                refs.append(node["$ref"])
            for value in node.values():
                walk(value)
        elif isinstance(node, list):
            for value in node:
                walk(value)

    walk(doc)
    assert refs
    for ref in refs:
        section, name = ref.removeprefix("#/components/").split("/")
        assert name in doc["components"][section], ref


def test_binary_values_are_in_the_document() -> None:
    doc = document(True)
    stream = doc["paths"]["/api/v1/services/{service}/properties/{path}/stream"]["get"]
    assert "multipart/x-mixed-replace" in stream["responses"]["200"]["content"]
    get = doc["paths"]["/api/v1/services/{service}/properties/{path}"]["get"]
    assert "raw" in [p["name"] for p in get["parameters"]]
    assert {"application/json", "application/octet-stream", "image/*"} <= set(
        get["responses"]["200"]["content"]
    )
    put = doc["paths"]["/api/v1/services/{service}/properties/{path}"]["put"]
    assert {"application/json", "application/octet-stream"} <= set(put["requestBody"]["content"])
    schemas = doc["components"]["schemas"]
    for name in ("Value", "Event"):
        assert schemas[name]["properties"]["data"]["contentEncoding"] == "base64"
        assert "media_type" in schemas[name]["properties"]
    model_property = schemas["Model"]["properties"]["properties"]["items"]["properties"]
    assert {"media_type", "max_size"} <= set(model_property)


# -- errors and bodies -------------------------------------------------------------------------


def test_error_statuses_follow_googles_mapping() -> None:
    assert {code.name: HTTP_STATUS[code] for code in Code} == {
        "OK": 200,
        "CANCELLED": 499,
        "UNKNOWN": 500,
        "INVALID_ARGUMENT": 400,
        "DEADLINE_EXCEEDED": 504,
        "NOT_FOUND": 404,
        "ALREADY_EXISTS": 409,
        "PERMISSION_DENIED": 403,
        "RESOURCE_EXHAUSTED": 429,
        "FAILED_PRECONDITION": 400,
        "ABORTED": 409,
        "OUT_OF_RANGE": 400,
        "UNIMPLEMENTED": 501,
        "INTERNAL": 500,
        "UNAVAILABLE": 503,
        "DATA_LOSS": 500,
        "UNAUTHENTICATED": 401,
    }


def test_a_set_body_carries_text_or_base64_bytes() -> None:
    assert parse_set_body(b'{"data": "AAEC/w=="}').value == b"\x00\x01\x02\xff"
    assert parse_set_body(b'{"data": ""}').value == b""
    assert parse_set_body(b'{"value": ""}').value == ""
    for body, words in (
        (b'{"data": "AAE"}', "base64"),
        (b'{"data": "AA\\nAA=="}', "base64"),
        (b'{"data": "AA-_"}', "base64"),
        (b'{"data": null}', "base64"),
        (b'{"data": "AA==", "value": "x"}', "both"),
        (b"{}", "'value'"),
    ):
        with pytest.raises(InvalidArgument, match=words):
            parse_set_body(body)


@pytest.mark.parametrize(
    ("declared", "served"),
    [
        ("image/png", "image/png"),
        ("Image/JPEG; q=1", "image/jpeg"),
        ("application/x-npy", "application/x-npy"),
        ("video/mp4", "video/mp4"),
        ("image/svg+xml", "application/octet-stream"),
        ("text/html", "application/octet-stream"),
        ("application/javascript", "application/octet-stream"),
        ("application/xhtml+xml", "application/octet-stream"),
        ("", "application/octet-stream"),
        ("image/png\r\nX-Evil: 1", "application/octet-stream"),
    ],
)
def test_a_raw_answer_is_served_only_as_a_type_a_browser_cannot_run(declared: str, served: str) -> None:
    assert served_type(declared) == served


def test_json_values_become_value_text() -> None:
    body = parse_set_body(b'{"value": [[1, 2.5], [true, "a"]], "parameters": {"times": 3, "frame": "robot"}}')
    assert body.value == "((1 2.5) (true a))"
    assert body.parameters == {"times": "3", "frame": "robot"}
    assert parse_set_body(b'{"value": 1e21}').value == "1e+21"
    with pytest.raises(InvalidArgument, match="Infinity"):
        parse_set_body(b'{"value": Infinity}')


@pytest.mark.parametrize(
    ("host", "loopback"),
    [
        ("localhost", True),
        ("LOCALHOST:8080", True),
        ("127.0.0.1", True),
        ("127.1.2.3:80", True),
        ("[::1]:8080", True),
        ("ui.localhost", True),
        ("localhost.example", False),
        ("", False),
        ("[::1", True),
        ("192.168.1.2", False),
        ("[2001:db8::1]:80", False),
    ],
)
def test_loopback_host_names(host: str, loopback: bool) -> None:
    assert is_loopback_host(host) is loopback


# -- console files -----------------------------------------------------------------------------


@pytest.fixture
def console_folder(tmp_path: Path) -> Path:
    root = tmp_path / "console"
    (root / "js").mkdir(parents=True)
    (root / "index.html").write_text("<!doctype html><html></html>")
    (root / "js" / "main.js").write_text("export const x = 1;\n")
    (root / "console.css").write_text("body {}\n")
    (root / "logo.svg").write_text("<svg/>")
    (root / "data.bin").write_bytes(b"\x00\x01")
    (root / ".secret").write_text("hidden")
    (tmp_path / "outside.txt").write_text("outside")
    os.symlink(tmp_path / "outside.txt", root / "escape.txt")
    return root


@pytest.mark.parametrize(
    "relative",
    [
        "../outside.txt",
        "js/../../outside.txt",
        "escape.txt",
        ".secret",
        "js",
        "js/",
        "",
        "nothing.js",
        "a\\b",
    ],
)
def test_only_files_inside_the_folder_are_found(console_folder: Path, relative: str) -> None:
    if relative == "":
        assert console_file(console_folder, relative).name == "index.html"
        return
    with pytest.raises(NotFound):
        console_file(console_folder, relative)


@pytest.fixture
async def console_server(console_folder: Path) -> AsyncIterator[TestServer]:
    app = web.Application()
    console = Console(console_folder)
    app.router.add_get("/", console.file)
    app.router.add_get("/console/{file:.*}", console.file)
    server = TestServer(app, host="127.0.0.1")
    await server.start_server()
    yield server
    await server.close()


@pytest.mark.parametrize(
    ("path", "content_type"),
    [
        ("/", "text/html; charset=utf-8"),
        ("/console/js/main.js", "text/javascript; charset=utf-8"),
        ("/console/console.css", "text/css; charset=utf-8"),
        ("/console/logo.svg", "image/svg+xml"),
        ("/console/data.bin", "application/octet-stream"),
    ],
)
async def test_console_files_have_their_content_type_and_no_cache(
    console_server: TestServer, path: str, content_type: str
) -> None:
    async with aiohttp.ClientSession() as http, http.get(console_server.make_url(path)) as response:
        assert response.status == 200
        assert response.headers["Content-Type"] == content_type
        assert response.headers["Cache-Control"] == "no-cache"
        assert response.headers["X-Content-Type-Options"] == "nosniff"


# -- in-process, through the test kit ------------------------------------------------------------


async def test_the_test_kit_serves_http_on_a_free_port_when_asked() -> None:
    config = Config(http=HttpSection(listen="127.0.0.1:0", console=False))
    async with running_gateway(Board(), name="board", config=config) as gateway:
        assert gateway.http is not None
        url = gateway.http.url
        assert url.startswith("http://127.0.0.1:") and not url.endswith(":0/")
        async with aiohttp.ClientSession(base_url=url) as http:
            put = await http.put(
                "/api/v1/services/board/properties/note",
                json={"value": "in process"},
                headers={"Content-Type": "application/json"},
            )
            assert put.status == 200
            async with http.get("/api/v1/services/board/properties/note") as got:
                assert (await got.json())["value"] == "in process"
            async with http.get("/") as console:
                assert console.status == 404  # console = false
    async with aiohttp.ClientSession() as http:
        with pytest.raises(aiohttp.ClientConnectionError):
            await http.get(url + "api/v1/health")  # stopped with the gateway


def test_check_config_checks_and_names_the_http_section(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from gateway.cli import main

    good = tmp_path / "good.toml"
    good.write_text('[http]\nlisten = "127.0.0.1:8081"\n')
    assert main(["check-config", str(good)]) == 0
    assert "HTTP on 127.0.0.1:8081" in capsys.readouterr().out
    bad = tmp_path / "bad.toml"
    bad.write_text('[http]\nlisten = "127.0.0.1:8081"\nmax_body = 0\nheartbeat = -1\n')
    assert main(["check-config", str(bad)]) == 2
    errors = capsys.readouterr().err.splitlines()
    assert sum("http.max_body" in line for line in errors) == 1
    assert sum("http.heartbeat" in line for line in errors) == 1


def test_the_open_files_limit_is_raised_to_the_hard_limit_and_shared_between_ports() -> None:
    import resource

    from gateway.connections import share_open_files

    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    top = soft if hard == resource.RLIM_INFINITY else hard
    try:
        resource.setrlimit(resource.RLIMIT_NOFILE, (top - 100, hard))  # a soft limit under the hard one
        wanted = {"http.max_connections": 10, "gateway.max_connections": 20}
        assert share_open_files(wanted, reserved=10) == wanted
        assert resource.getrlimit(resource.RLIMIT_NOFILE)[0] == top
        # Shares that do not fit beside what is reserved are lowered in proportion.
        shares = share_open_files({"http.max_connections": top, "gateway.max_connections": top}, reserved=100)
        assert shares["http.max_connections"] == shares["gateway.max_connections"] == (top - 100) // 2
    finally:
        resource.setrlimit(resource.RLIMIT_NOFILE, (soft, hard))


class Bins(Resource):
    """A binary property of any bytes and one of PNG pictures."""

    resource_type = "store"
    blob: Annotated[bytes, Prop(doc="any bytes")] = b""
    picture: Annotated[bytes, Prop(media_type="image/png", doc="a picture")] = b""


async def test_a_raw_set_of_any_bytes_takes_any_content_type() -> None:
    config = Config(http=HttpSection(listen="127.0.0.1:0", console=False))
    async with running_gateway(Bins(), name="bins", config=config) as gateway:
        assert gateway.http is not None
        async with aiohttp.ClientSession(base_url=gateway.http.url) as http:
            jpeg = b"\xff\xd8\xff\xe0 a picture"
            path = "/api/v1/services/bins/properties/"
            async with http.put(path + "blob", data=jpeg, headers={"Content-Type": "image/jpeg"}) as put:
                assert put.status == 200, await put.text()
            async with http.get(path + "blob", params={"raw": "1"}) as got:
                assert await got.read() == jpeg
            # A form's type is refused all the same (no cross-origin Set without a preflight).
            async with http.put(path + "blob", data=jpeg, headers={"Content-Type": "text/plain"}) as put:
                assert put.status == 400
            # A property of one media type takes that one or octet-stream, and says so once each.
            async with http.put(path + "picture", data=jpeg, headers={"Content-Type": "image/jpeg"}) as put:
                assert put.status == 400
                message = (await put.json())["error"]["message"]
            assert "Content-Type: image/png or application/octet-stream" in message, message
            assert message.count("application/octet-stream") == 1, message


async def test_a_client_gone_before_its_answer_is_written_is_no_error_to_log(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A page closed just as its event stream opened: the headers' write finds the transport closing."""
    from aiohttp.client_exceptions import ClientConnectionResetError
    from aiohttp.test_utils import make_mocked_request

    async def gone(request: web.Request) -> web.StreamResponse:
        raise ClientConnectionResetError("Cannot write to closing transport")

    config = Config(http=HttpSection(listen="127.0.0.1:0", console=False))
    async with running_gateway(Board(), name="board", config=config) as gateway:
        assert gateway.http is not None
        request = make_mocked_request("GET", "/api/v1/events", headers={"Host": "127.0.0.1"})
        with caplog.at_level("DEBUG"):
            answer = await gateway.http._answer(request, gone)
    assert answer.status == 499
    assert not [r for r in caplog.records if r.levelname in ("ERROR", "WARNING")], caplog.text
