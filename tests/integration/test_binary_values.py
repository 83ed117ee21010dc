"""Binary values through a real gateway process: bytes in, the same bytes out, on every path.

A property of type ``bytes`` carries raw bytes in the contract's ``data`` field (``value`` stays
""); text properties are unchanged. The service is ``support.blobs:Blobs``.
"""

from __future__ import annotations

import asyncio
import base64
import json
import os
import pty
import random
import subprocess
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import grpc
import psutil
import pytest
from google.protobuf import descriptor_pb2, descriptor_pool, message_factory
from support.blobs import start_blobs
from support.gateway_process import GatewayProcess
from support.psctl import PSCTL, psctl

from clients import AsyncClient, Client
from clients.errors import InvalidArgument, ResourceExhausted
from protos.propertyservice.v1 import property_service_pb2 as pb
from protos.propertyservice.v1 import property_service_pb2_grpc as pb_grpc

WAIT = 20.0
#: Every byte value, in an order that is not the natural one, plus some random bytes.
EVERY_BYTE = bytes(range(256))[::-1] + random.Random(12).randbytes(100_000)


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_blobs(tmp_path_factory.mktemp("blobs"))
    yield gw
    gw.stop()


@pytest.fixture
async def stub(gateway: GatewayProcess) -> AsyncIterator[pb_grpc.PropertyServiceStub]:
    async with grpc.aio.insecure_channel(gateway.address) as channel:
        yield pb_grpc.PropertyServiceStub(channel)


async def expect(code: grpc.StatusCode, call: object) -> str:
    with pytest.raises(grpc.aio.AioRpcError) as err:
        await call  # type: ignore[misc]
    assert err.value.code() == code, err.value.details()
    return err.value.details() or ""


async def test_unary_get_and_set_carry_the_bytes_in_data(stub: pb_grpc.PropertyServiceStub) -> None:
    answer = await stub.Set(pb.SetRequest(service="blobs", property="picture", data=EVERY_BYTE), timeout=WAIT)
    assert answer.HasField("data") and answer.data == EVERY_BYTE and answer.value == ""
    got = await stub.Get(pb.GetRequest(service="blobs", property="picture"), timeout=WAIT)
    assert got.HasField("data") and got.data == EVERY_BYTE and got.value == ""
    # An empty binary value is still binary: `data` is present, and empty.
    await stub.Set(pb.SetRequest(service="blobs", property="small", data=b""), timeout=WAIT)
    empty = await stub.Get(pb.GetRequest(service="blobs", property="small"), timeout=WAIT)
    assert empty.HasField("data") and empty.data == b""
    # Text is unchanged: no `data` on a text property.
    await stub.Set(pb.SetRequest(service="blobs", property="note", value="héllo"), timeout=WAIT)
    text = await stub.Get(pb.GetRequest(service="blobs", property="note"), timeout=WAIT)
    assert not text.HasField("data") and text.value == "héllo"
    # A Get of several paths carries each value in its own form.
    both = await stub.Get(
        pb.GetRequest(service="blobs", property="note", more=[pb.PropertyRef(property="picture")]),
        timeout=WAIT,
    )
    assert both.value == "héllo" and not both.HasField("data")
    assert both.more[0].HasField("data") and both.more[0].data == EVERY_BYTE
    # An action takes bytes and answers bytes; a query answers text about them.
    echoed = await stub.Set(
        pb.SetRequest(service="blobs", property="echo", data=b"\x00\x01\xff"), timeout=WAIT
    )
    assert echoed.data == b"\xff\x01\x00"
    empty_answer = await stub.Set(pb.SetRequest(service="blobs", property="echo", data=b""), timeout=WAIT)
    assert empty_answer.HasField("data") and empty_answer.data == b""  # empty, and still binary
    checksum = await stub.Get(pb.GetRequest(service="blobs", property="checksum"), timeout=WAIT)
    assert checksum.value.startswith(f"({len(EVERY_BYTE)} ")


async def test_describe_and_metadata_say_why_an_old_client_sees_an_empty_value(
    gateway: GatewayProcess,
) -> None:
    channel = grpc.aio.insecure_channel(gateway.address)
    try:
        await _describe_and_old_client(channel, pb_grpc.PropertyServiceStub(channel))
    finally:
        await channel.close()


async def _describe_and_old_client(channel: grpc.aio.Channel, stub: pb_grpc.PropertyServiceStub) -> None:
    model = await stub.Describe(pb.DescribeRequest(service="blobs"), timeout=WAIT)
    info = {p.name: p for p in model.properties}
    assert (info["picture"].type, info["picture"].media_type) == ("bytes", "image/png")
    assert info["picture"].max_size == 8 * 1024 * 1024 and info["picture"].gui == "image"
    assert (info["frame"].type, info["frame"].access) == ("bytes", pb.ACCESS_READ)
    assert (info["small"].type, info["small"].max_size, info["small"].media_type) == ("bytes", 16, "")
    assert (info["note"].type, info["note"].media_type, info["note"].max_size) == ("text", "", 0)
    assert info["echo"].value.type == "bytes"
    media = await stub.Get(pb.GetRequest(service="blobs", property="picture.media_type"), timeout=WAIT)
    assert media.value == "image/png"
    await expect(
        grpc.StatusCode.NOT_FOUND, stub.Get(pb.GetRequest(service="blobs", property="note.media_type"))
    )

    # A client built before `data` existed: the same bytes on the wire, read with the old schema.
    await stub.Set(pb.SetRequest(service="blobs", property="picture", data=b"\x89PNG"), timeout=WAIT)
    old_get_response = _old_schema_message("GetResponse")
    raw = await channel.unary_unary(
        "/propertyservice.v1.PropertyService/Get",
        request_serializer=pb.GetRequest.SerializeToString,
        response_deserializer=lambda data: data,
    )(pb.GetRequest(service="blobs", property="picture"), timeout=WAIT)
    old = old_get_response.FromString(raw)
    assert old.value == ""  # what an old client shows; Describe says the type is bytes
    # The bytes are there, in a field it does not know and keeps (it would pass them on whole).
    assert old.SerializeToString() == raw and b"\x89PNG" in raw


def _old_schema_message(name: str) -> type:
    """``GetResponse`` as the contract had it before binary values: ``value`` and ``more`` only."""
    field = descriptor_pb2.FieldDescriptorProto
    proto = descriptor_pb2.FileDescriptorProto(
        name="old/property_service.proto", package="old.v1", syntax="proto3"
    )
    value = proto.message_type.add(name="PropertyValue")
    for number, text in enumerate(("service", "property", "value"), start=1):
        value.field.add(name=text, number=number, type=field.TYPE_STRING, label=field.LABEL_OPTIONAL)
    response = proto.message_type.add(name=name)
    response.field.add(name="value", number=1, type=field.TYPE_STRING, label=field.LABEL_OPTIONAL)
    response.field.add(
        name="more",
        number=2,
        type=field.TYPE_MESSAGE,
        type_name=".old.v1.PropertyValue",
        label=field.LABEL_REPEATED,
    )
    pool = descriptor_pool.DescriptorPool()
    pool.Add(proto)
    return message_factory.GetMessageClass(pool.FindMessageTypeByName(f"old.v1.{name}"))


async def test_the_wrong_form_and_sizes_over_the_limits_are_refused(
    stub: pb_grpc.PropertyServiceStub,
) -> None:
    text_on_bytes = await expect(
        grpc.StatusCode.INVALID_ARGUMENT,
        stub.Set(pb.SetRequest(service="blobs", property="picture", value="not bytes")),
    )
    assert "`picture` is binary (type bytes, image/png): send its value as bytes" in text_on_bytes
    bytes_on_text = await expect(
        grpc.StatusCode.INVALID_ARGUMENT, stub.Set(pb.SetRequest(service="blobs", property="note", data=b"x"))
    )
    assert "`note` is text (type text): send its value as text" in bytes_on_text
    both = await expect(
        grpc.StatusCode.INVALID_ARGUMENT,
        stub.Set(pb.SetRequest(service="blobs", property="picture", value="x", data=b"x")),
    )
    assert "either text (value) or bytes (data)" in both
    over = await expect(
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        stub.Set(pb.SetRequest(service="blobs", property="small", data=b"x" * 17)),
    )
    assert over == "`small`: a value of 17 bytes is more than `small` takes (16 bytes)"
    # An answer bigger than one message may carry: refused by name, before the client's own limit.
    too_big = await expect(
        grpc.StatusCode.RESOURCE_EXHAUSTED,
        stub.Get(pb.GetRequest(service="blobs", property="big", parameters={"size": str(5 * 1024 * 1024)})),
    )
    assert "blobs: get big: the answer is 524" in too_big and "more than one message may carry" in too_big
    # A value just under the limit travels.
    fits = await stub.Get(
        pb.GetRequest(service="blobs", property="big", parameters={"size": str(4 * 1024 * 1024 - 2048)}),
        timeout=WAIT,
    )
    assert fits.data == bytes(4 * 1024 * 1024 - 2048)


async def test_listen_events_carry_bytes(stub: pb_grpc.PropertyServiceStub) -> None:
    await stub.Set(pb.SetRequest(service="blobs", property="picture", data=b"first"), timeout=WAIT)
    call = stub.Listen(
        pb.ListenRequest(
            service="blobs", property="picture", more=[pb.PropertyRef(service="blobs", property="note")]
        )
    )
    try:
        current: dict[str, pb.Event] = {}
        while True:
            response = await asyncio.wait_for(call.read(), WAIT)
            current.update({e.property: e for e in response.events})
            if response.sync:
                break
        assert current["picture"].HasField("data") and current["picture"].data == b"first"
        assert not current["note"].HasField("data")
        await stub.Set(pb.SetRequest(service="blobs", property="picture", data=EVERY_BYTE), timeout=WAIT)
        response = await asyncio.wait_for(call.read(), WAIT)
        (event,) = response.events
        assert (event.property, event.data, event.value) == ("picture", EVERY_BYTE, "")
    finally:
        call.cancel()


async def test_session_replies_and_listens_carry_bytes(gateway: GatewayProcess) -> None:
    async with AsyncClient(gateway.address, timeout=WAIT) as client, client.session() as session:
        assert await session.set("blobs", "picture", EVERY_BYTE) == EVERY_BYTE
        assert await session.get("blobs", "picture") == EVERY_BYTE
        assert await session.get_many([("blobs", "picture"), ("blobs", "note")]) == [
            EVERY_BYTE,
            await session.get("blobs", "note"),
        ]
        with pytest.raises(InvalidArgument, match="send its value as bytes"):
            await session.set("blobs", "picture", "text")
        with pytest.raises(ResourceExhausted, match="more than one message may carry"):
            await session.get("blobs", "big", size=5 * 1024 * 1024)
        events = session.listen("blobs", "picture", updates_only=True)
        try:
            waiting = asyncio.ensure_future(anext(events))
            await asyncio.sleep(0.2)  # the Listen is in place before the change
            await session.set("blobs", "picture", b"\x00" * 3)
            event = await asyncio.wait_for(waiting, WAIT)
            assert event.value == b"\x00" * 3
        finally:
            await events.aclose()


async def test_the_aio_sdk_reads_and_writes_bytes(gateway: GatewayProcess) -> None:
    async with AsyncClient(gateway.address, timeout=WAIT) as client:
        assert await client.set("blobs", "picture", bytearray(EVERY_BYTE)) == EVERY_BYTE
        assert await client.get("blobs", "picture") == EVERY_BYTE
        assert await client.get_bytes("blobs", "picture") == EVERY_BYTE
        assert await client.set("blobs", "echo", memoryview(b"abc")) == b"cba"
        with pytest.raises(ValueError, match="not bytes"):
            await client.get_bytes("blobs", "note")
        model = {p.name: p for p in (await client.describe("blobs")).properties}
        assert (model["picture"].type, model["picture"].media_type) == ("bytes", "image/png")
        events = client.listen("blobs", "picture")
        try:
            assert (await asyncio.wait_for(anext(events), WAIT)).value == EVERY_BYTE
        finally:
            await events.aclose()


def test_the_sync_sdk_reads_and_writes_bytes(gateway: GatewayProcess) -> None:
    with Client(gateway.address, timeout=WAIT) as client:
        client.set("blobs", "picture", b"sync bytes \x00\xff")
        assert client.get("blobs", "picture") == b"sync bytes \x00\xff"
        assert client.get_bytes("blobs", "picture") == b"sync bytes \x00\xff"
        with client.session() as session:
            assert session.set("blobs", "echo", b"\x01\x02") == b"\x02\x01"
        events = client.listen("blobs", "picture")
        try:
            assert next(iter(events)).value == b"sync bytes \x00\xff"
        finally:
            events.close()


async def test_a_binary_property_works_through_a_federated_gateway(
    gateway: GatewayProcess, tmp_path: Path
) -> None:
    front = start_blobs(tmp_path, f'[[services]]\nname = "far"\nurl = "grpc://{gateway.address}/blobs"\n')
    try:
        async with AsyncClient(front.address, timeout=WAIT) as client:
            assert await client.set("far", "picture", EVERY_BYTE) == EVERY_BYTE
            assert await client.get("far", "picture") == EVERY_BYTE
            await client.set("far", "note", "text as before")
            assert await client.get("far", "note") == "text as before"
            with pytest.raises(InvalidArgument, match="send its value as bytes"):
                await client.set("far", "picture", "text")
            model = {p.name: p for p in (await client.describe("far")).properties}
            assert (model["picture"].type, model["picture"].media_type) == ("bytes", "image/png")
            events = client.listen("far", "picture")
            try:
                assert (await asyncio.wait_for(anext(events), WAIT)).value == EVERY_BYTE
                await client.set("far", "picture", b"changed \x00")
                assert (await asyncio.wait_for(anext(events), WAIT)).value == b"changed \x00"
            finally:
                await events.aclose()
    finally:
        front.stop()


def test_a_value_too_big_for_the_gateway_to_receive_is_refused(gateway: GatewayProcess) -> None:
    with grpc.insecure_channel(
        gateway.address, options=[("grpc.max_send_message_length", 16 * 1024 * 1024)]
    ) as channel:
        stub = pb_grpc.PropertyServiceStub(channel)
        with pytest.raises(grpc.RpcError) as err:
            stub.Set(
                pb.SetRequest(service="blobs", property="picture", data=os.urandom(5 * 1024 * 1024)),
                timeout=WAIT,
            )
        assert err.value.code() == grpc.StatusCode.RESOURCE_EXHAUSTED


async def test_a_slow_reader_of_a_large_fast_binary_value_holds_the_gateways_memory_flat(
    tmp_path: Path,
) -> None:
    """200 KB frames at 50 a second, a reader that stops reading for 8 s: it gets the latest frame
    (conflation), and the gateway does not queue the 80 MB it missed."""
    gw = start_blobs(tmp_path)
    gateway = psutil.Process(gw.proc.pid)
    try:
        async with grpc.aio.insecure_channel(gw.address) as channel:
            stub = pb_grpc.PropertyServiceStub(channel)
            for name, value in (("frame_bytes", "200000"), ("rate_hz", "50"), ("stream", "true")):
                await stub.Set(pb.SetRequest(service="blobs", property=name, value=value), timeout=WAIT)
            call = stub.Listen(pb.ListenRequest(service="blobs", property="frame"))
            try:
                # A reader that keeps up, for two seconds: the gateway's working set.
                loop = asyncio.get_running_loop()
                until = loop.time() + 2.0
                while loop.time() < until:
                    await asyncio.wait_for(call.read(), WAIT)
                before = gateway.memory_info().rss
                await asyncio.sleep(8.0)  # the reader stops reading: 400 frames, 80 MB, go by
                stalled = gateway.memory_info().rss
                # Reading again: what waited in the transport's buffers, then the latest frames,
                # with the ones missed counted as conflated.
                conflated = 0
                seen = 0
                while conflated < 100:
                    response = await asyncio.wait_for(call.read(), WAIT)
                    for event in response.events:
                        assert event.HasField("data") and len(event.data) == 200_000
                        conflated += event.conflated
                        seen += 1
                assert seen < 100, f"{seen} frames were kept for the slow reader"
            finally:
                call.cancel()
            await stub.Set(pb.SetRequest(service="blobs", property="stream", value="false"), timeout=WAIT)
    finally:
        gw.stop()
    growth = stalled - before
    print(
        f"rss before {before / 1e6:.1f} MB, after stall {stalled / 1e6:.1f} MB; "
        f"{seen} frames read, {conflated} conflated"
    )
    assert growth < 25 * 1024 * 1024, f"the gateway grew by {growth / 1e6:.1f} MB while the reader stalled"


def test_psctl_writes_a_binary_value_into_a_file_and_sends_a_files_bytes(
    gateway: GatewayProcess, tmp_path: Path
) -> None:
    source = tmp_path / "in.png"
    source.write_bytes(EVERY_BYTE)
    done = psctl(gateway.address, "set", "blobs", "picture", "--file", str(source))
    assert done.returncode == 0, done.stderr
    assert done.stdout == f"<{len(EVERY_BYTE)} bytes>\n"  # the answer, never raw bytes on a line
    out = tmp_path / "out.png"
    done = psctl(gateway.address, "get", "blobs", "picture", "--output", str(out))
    assert done.returncode == 0, done.stderr
    assert out.read_bytes() == EVERY_BYTE
    # @FILE is --file; @@ starts a text with @.
    (tmp_path / "small.bin").write_bytes(b"\x00\x01")
    assert psctl(gateway.address, "set", "blobs", "small", f"@{tmp_path / 'small.bin'}").returncode == 0
    assert psctl(gateway.address, "set", "blobs", "note", "@@home").returncode == 0
    assert psctl(gateway.address, "get", "blobs", "note").stdout == "@home\n"
    # A file sent to a text property goes as its UTF-8 text.
    (tmp_path / "note.txt").write_text("from a file ✓")
    assert (
        psctl(gateway.address, "set", "blobs", "note", "--file", str(tmp_path / "note.txt")).returncode == 0
    )
    assert psctl(gateway.address, "get", "blobs", "note").stdout == "from a file ✓\n"
    (tmp_path / "bad.txt").write_bytes(b"\xff\xfe")
    refused = psctl(gateway.address, "set", "blobs", "note", "--file", str(tmp_path / "bad.txt"))
    assert refused.returncode == 2 and "takes text (type text)" in refused.stderr
    # To a pipe the bytes go as they are; several paths and JSON show them without raw bytes.
    piped = subprocess.run(
        [*PSCTL, "-t", gateway.address, "get", "blobs", "picture"],
        capture_output=True,
        timeout=60,
        check=False,
    )
    assert piped.returncode == 0 and piped.stdout == EVERY_BYTE
    lines = psctl(gateway.address, "get", "blobs", "picture", "note").stdout.splitlines()
    assert lines == [f"picture = <{len(EVERY_BYTE)} bytes>", "note = from a file ✓"]
    as_json = json.loads(psctl(gateway.address, "--json", "get", "blobs", "picture").stdout)
    assert base64.b64decode(as_json["data"]) == EVERY_BYTE and "value" not in as_json


def test_psctl_shows_the_model_of_a_binary_property(gateway: GatewayProcess) -> None:
    table = psctl(gateway.address, "ls", "-l", "blobs").stdout.splitlines()
    picture = next(line.split() for line in table if line.startswith("picture "))
    assert picture[:5] == ["picture", "bytes(image/png)", "read-write", "-", "at"]
    rows = {r["name"]: r for r in json.loads(psctl(gateway.address, "--json", "ls", "-l", "blobs").stdout)}
    assert (rows["picture"]["media_type"], rows["picture"]["max_size"]) == ("image/png", 8 * 1024 * 1024)
    assert (rows["note"]["media_type"], rows["note"]["max_size"]) == ("", 0)


def test_psctl_refuses_to_dump_a_binary_value_on_a_terminal(gateway: GatewayProcess) -> None:
    with Client(gateway.address, timeout=WAIT) as client:
        client.set("blobs", "picture", EVERY_BYTE)
    primary, secondary = pty.openpty()
    try:
        done = subprocess.run(
            [*PSCTL, "-t", gateway.address, "get", "blobs", "picture"],
            stdout=secondary,
            stderr=subprocess.PIPE,
            text=True,
            timeout=60,
            check=False,
        )
    finally:
        os.close(secondary)
        os.close(primary)
    assert done.returncode == 2
    assert f"blobs picture is binary ({len(EVERY_BYTE)} bytes of image/png): not written to a terminal" in (
        done.stderr
    )
    assert "--output FILE" in done.stderr
