"""Binary values in one process: the class wrapper, the model's wire forms, and Listen batching."""

from __future__ import annotations

from typing import Annotated

import pytest

from gateway.engine.events import SharedEvent
from gateway.engine.listen.stream import within
from gateway.engine.listen.topics import Topic
from gateway.engine.sizes import BATCH_BYTES, MAX_BINARY_SIZE
from gateway.fronts.grpc_v1.listen_encoding import encode_events
from gateway.wire_values import put, received
from protos.propertyservice.v1 import property_service_pb2 as pb
from services.kernel.backend import Change
from services.kernel.conflation import ConflatingQueue, Slot
from services.kernel.core import LocalService, Prop, Resource, action, query
from services.kernel.errors import InvalidArgument, NotFound, ResourceExhausted
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.model_codec import model_from_proto, model_from_text, model_to_proto, model_to_text
from services.kernel.values import Value, as_text, loggable, value_size


class Camera(Resource):
    """A camera whose frame is bytes, beside text and numbers."""

    resource_type = "camera"
    frame: Annotated[bytes, Prop(readonly=True, media_type="image/jpeg")] = b""
    snapshot: Annotated[bytes, Prop(media_type="image/png", max_size=8)] = b""
    quality: int = 80
    label: str = ""

    @property
    def thumbnail(self) -> Annotated[bytes, Prop(media_type="image/jpeg")]:
        """The frame's first bytes."""
        return self.frame[:4]

    @query
    def crop(self, size: int = 2) -> Annotated[bytes, Prop(media_type="image/jpeg")]:
        """The frame's first ``size`` bytes."""
        return self.frame[:size]

    @action
    def upload(self, data: Annotated[bytes, Prop(media_type="application/x-npy", max_size=4)]) -> int:
        """Take bytes; answer how many."""
        return len(data)


@pytest.fixture
def camera() -> Camera:
    return Camera()


@pytest.fixture
def svc(camera: Camera) -> LocalService:
    return LocalService(camera)


async def test_a_bytes_property_reads_and_writes_bytes(svc: LocalService, camera: Camera) -> None:
    camera.frame = b"\xff\xd8\xff\xe0"
    assert await svc.get("frame") == b"\xff\xd8\xff\xe0"
    assert await svc.get("thumbnail") == b"\xff\xd8\xff\xe0"
    assert await svc.get("crop", {"size": "1"}) == b"\xff"
    assert await svc.set("snapshot", b"\x00\x01") == b"\x00\x01"
    assert camera.snapshot == b"\x00\x01"
    assert await svc.set("upload", b"\x01\x02\x03") == "3"
    assert await svc.get("quality") == "80"  # text stays text


async def test_media_type_is_metadata_of_binary_properties_only(svc: LocalService) -> None:
    assert await svc.get("frame.media_type") == "image/jpeg"
    assert await svc.get("snapshot.media_type") == "image/png"
    assert await svc.get("crop.media_type") == "image/jpeg"
    with pytest.raises(NotFound):
        await svc.get("quality.media_type")
    model = {p.name: p for p in (await svc.describe()).properties}
    assert (model["frame"].type, model["frame"].media_type, model["frame"].gui) == (
        "bytes",
        "image/jpeg",
        "image",
    )
    assert (model["snapshot"].max_size, model["upload"].max_size) == (8, 4)
    assert model["upload"].value is not None and model["upload"].value.type == "bytes"
    assert model["upload"].media_type == "application/x-npy"
    assert (model["crop"].type, model["crop"].access) == ("bytes", Access.QUERY)
    assert (model["quality"].type, model["quality"].media_type, model["quality"].max_size) == (
        "integer",
        "",
        0,
    )


async def test_the_wrong_form_and_an_oversized_value_are_refused_by_name(svc: LocalService) -> None:
    with pytest.raises(
        InvalidArgument, match=r"`snapshot` is binary \(type bytes, image/png\): send its value as bytes"
    ):
        await svc.set("snapshot", "text")
    with pytest.raises(InvalidArgument, match=r"`quality` is text \(type integer\): send its value as text"):
        await svc.set("quality", b"80")
    with pytest.raises(InvalidArgument, match="`upload` is binary"):
        await svc.set("upload", "abc")
    with pytest.raises(
        ResourceExhausted, match=r"`snapshot`: a value of 9 bytes is more than `snapshot` takes \(8 bytes\)"
    ):
        await svc.set("snapshot", bytes(9))
    with pytest.raises(ResourceExhausted, match="5 bytes"):
        await svc.set("upload", bytes(5))


async def test_the_default_limit_is_one_message(svc: LocalService) -> None:
    class Big(Resource):
        blob: bytes = b""

    big = LocalService(Big())
    assert await big.set("blob", bytes(MAX_BINARY_SIZE)) == bytes(MAX_BINARY_SIZE)
    with pytest.raises(ResourceExhausted, match=f"{MAX_BINARY_SIZE + 1} bytes"):
        await big.set("blob", bytes(MAX_BINARY_SIZE + 1))


def test_media_type_on_a_text_value_is_a_mistake_found_when_the_class_is_served() -> None:
    class Wrong(Resource):
        name: Annotated[str, Prop(media_type="image/png")] = ""

    with pytest.raises(TypeError, match="media_type and max_size are for a bytes value, not text"):
        LocalService(Wrong())


async def test_listeners_hear_bytes(svc: LocalService, camera: Camera) -> None:
    heard: list[Change] = []
    sub = await svc.listen("frame", heard.append)
    try:
        camera.frame = b"\x01"
        camera.frame = b"\x01"  # the same bytes: no change
        camera.frame = b"\x02\x03"
        assert [c.value for c in heard] == [b"\x01", b"\x02\x03"]
    finally:
        await sub.close()


def _waiting(value: Value) -> Slot[SharedEvent]:
    """What a Listen stream's queue holds for one new value of cam/frame."""
    queue: ConflatingQueue[int, SharedEvent] = ConflatingQueue()
    queue.put(0, SharedEvent("cam", "frame", value, 0))
    slot = queue.get(0)
    assert slot is not None
    return slot


def test_a_listen_batch_counts_the_bytes_of_binary_values() -> None:
    topic = Topic(("cam", "frame", ()), backend=None)  # type: ignore[arg-type]
    frame = bytes(300_000)
    items: list[tuple[Topic, Slot[SharedEvent]]] = [(topic, _waiting(frame)) for _ in range(10)]
    batch, size = within(items)
    assert len(batch) == BATCH_BYTES // 300_100 and size <= BATCH_BYTES
    response = encode_events(batch, 0)
    assert all(e.HasField("data") and e.data == frame and e.value == "" for e in response.events)
    assert response.ByteSize() <= BATCH_BYTES + 1024
    # Text and bytes side by side: each in its own field.
    mixed = encode_events([(topic, _waiting("(1 2)")), (topic, _waiting(b""))], 0)
    assert not mixed.events[0].HasField("data") and mixed.events[0].value == "(1 2)"
    assert mixed.events[1].HasField("data") and mixed.events[1].data == b""


def test_wire_values_put_bytes_in_data_and_text_in_value() -> None:
    response = pb.GetResponse()
    put(response, b"")
    assert response.HasField("data") and received(response) == b""
    text = pb.SetRequest(value="x")
    assert received(text) == "x"
    with pytest.raises(InvalidArgument, match="not both"):
        received(pb.SetRequest(value="x", data=b"y"))


def test_the_model_carries_media_type_and_max_size_on_both_wires() -> None:
    model = ServiceModel(
        type="camera",
        properties=(
            PropertyModel("frame", "bytes", Access.READ, media_type="image/jpeg", max_size=65536),
            PropertyModel("quality", "integer", Access.READ_WRITE),
        ),
    )
    assert model_from_proto(model_to_proto(model)) == model
    assert model_from_text(model_to_text(model), "camera") == model
    assert "(media_type image/jpeg) (max_size 65536)" in model_to_text(model)


def test_log_views_and_sizes_of_values() -> None:
    assert loggable(b"\x00" * 2048, "image/jpeg") == "<2048 bytes image/jpeg>"
    assert loggable(b"\x00") == "<1 bytes>"
    assert loggable("text") == "text"
    assert (value_size("é"), value_size(b"\xff\xfe")) == (2, 2)
    assert as_text("x") == "x"
    with pytest.raises(InvalidArgument, match="binary"):
        as_text(b"x", "location")
