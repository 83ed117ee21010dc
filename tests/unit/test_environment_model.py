"""The environment model: grid layers, heat map and properties, alone and through an in-process gateway."""

from __future__ import annotations

import io

import numpy as np
import pytest
from PIL import Image
from support.waiting import wait_until

from clients import AsyncClient
from clients.errors import InvalidArgument as InvalidArgumentError
from gateway.testing import serve
from services.apps.catalog import create
from services.apps.environment import EnvironmentModel, GridSpec, HitLayer, MeanLayer, heat_map_png, to_npy
from services.apps.environment.observations import parse_marker_list, write_marker_list
from services.kernel.backend import Change
from services.kernel.core import serve as serve_backend
from services.kernel.errors import InvalidArgument
from services.kernel.values import parse_list, parse_marker


class Clock:
    """A clock the test moves by hand."""

    def __init__(self) -> None:
        self.now = 1000.0

    def __call__(self) -> float:
        return self.now


def test_the_mean_layer_keeps_a_running_mean_and_a_count_per_cell() -> None:
    spec = GridSpec(origin=(0.0, 0.0), cell=1.0, shape=(2, 3))
    layer = MeanLayer("temperature", spec, unit="degC")
    for value in (20.0, 22.0, 24.0):
        assert layer.add(0.5, 0.5, value)
    assert layer.add(2.9, 1.1, 30.0)  # row 1 (y from 1 to 2), column 2
    assert not layer.add(3.0, 0.5, 99.0)  # x = 3 is past the last column
    assert not layer.add(-0.01, 0.5, 99.0)
    values = layer.values()
    assert values.dtype == np.float32 and values.shape == (2, 3)
    assert values[0, 0] == pytest.approx(22.0) and values[1, 2] == pytest.approx(30.0)
    assert np.isnan(values[0, 1]) and int(np.isnan(values).sum()) == 4
    assert layer.counts[0, 0] == 3 and layer.counts[1, 2] == 1
    assert (layer.filled, layer.total, layer.outside) == (2, 4, 2)
    info = dict((k, v) for k, v in layer.info())
    assert info["min"] == pytest.approx(22.0) and info["max"] == pytest.approx(30.0)
    assert info["shape"] == [2, 3] and info["origin"] == [0.0, 0.0]


def test_hit_layer_counts_sightings() -> None:
    layer = HitLayer("occupancy", GridSpec(origin=(-1.0, -1.0), cell=0.5, shape=(4, 4)))
    for _ in range(3):
        layer.add(0.1, 0.1)
    layer.add(-0.9, 0.9)
    values = layer.values()
    assert values[2, 2] == 3.0 and values[3, 0] == 1.0 and values.sum() == 4.0


def test_npy_decodes_to_the_same_float32_array() -> None:
    layer = MeanLayer("t", GridSpec(origin=(0.0, 0.0), cell=1.0, shape=(3, 4)))
    layer.add(1.5, 2.5, 21.25)
    decoded = np.load(io.BytesIO(to_npy(layer.values())), allow_pickle=False)
    assert decoded.dtype == np.float32 and decoded.shape == (3, 4)
    np.testing.assert_array_equal(decoded, layer.values())  # NaN where no reading, compared as equal
    assert decoded[2, 1] == np.float32(21.25)


def test_the_heat_map_is_a_png_north_up_with_empty_cells_transparent() -> None:
    values = np.full((2, 3), np.nan, dtype=np.float32)
    values[0, 0] = 10.0  # south-west: the bottom left of the picture
    values[1, 2] = 30.0  # north-east: the top right
    image = Image.open(io.BytesIO(heat_map_png(values)))
    assert image.format == "PNG" and image.mode == "RGBA"
    width, height = image.size
    assert width / height == pytest.approx(3 / 2) and max(width, height) >= 300
    low = image.getpixel((2, height - 3))
    high = image.getpixel((width - 3, 2))
    empty = image.getpixel((width - 3, height - 3))
    assert low[3] == 255 and high[3] == 255 and empty[3] == 0
    assert low[2] > low[0]  # blue at the low end
    assert high[0] > high[2]  # red at the high end


def test_grid_limits_are_checked() -> None:
    with pytest.raises(ValueError, match="limit is 1000000"):
        GridSpec(shape=(2000, 2000))
    with pytest.raises(ValueError, match="positive"):
        GridSpec(cell=0.0)
    with pytest.raises(InvalidArgument, match="grid shape"):
        EnvironmentModel(grid={"shape": [10]})


def test_bad_options_get_clear_errors() -> None:
    with pytest.raises(InvalidArgument, match=r"readings\[0\].layer"):
        EnvironmentModel(readings=[{"selector": "thermo1 data", "layer": "occupancy"}])
    with pytest.raises(InvalidArgument, match="ttl must be"):
        EnvironmentModel(ttl=0)
    with pytest.raises(InvalidArgument, match="needs a directory"):
        EnvironmentModel(markers=["camera1"])
    with pytest.raises(InvalidArgument, match="runs only inside a gateway"):
        create("environment", markers=["camera1"])
    with pytest.raises(InvalidArgument, match="'clock' is not an option"):
        create("environment", clock=lambda: 0.0)


async def test_markers_appear_and_expire_on_the_injected_clock() -> None:
    clock = Clock()
    model = EnvironmentModel(ttl=10.0, clock=clock)
    async with serve(model, name="env") as client:
        events = client.listen("env", "markers.*")
        try:
            marker = (
                "<marker><id>crate</id><class>box</class><location>(1 2)</location>"
                "<color>(1 0 0)</color></marker>"
            )
            assert await client.set("env", "observe", marker, source="camera9") == "crate"
            event = await anext(events)
            assert event.property == "markers.crate" and not event.removed
            fused = parse_marker(event.value)
            assert fused.get("class") == "box" and fused.get("color") == "(1 0 0)"
            assert fused.get("source") == "camera9" and fused.get("count") == "1"
            assert fused.get("location") == "(1 2 0)"
            assert await client.get("env", "markers") == "(crate)"
            assert await client.get("env", "count") == "1"
            clock.now += 10.5
            assert model.expire() == ["crate"]
            event = await anext(events)
            assert event.property == "markers.crate" and event.removed
        finally:
            await events.aclose()
        assert await client.get("env", "markers") == "()"
        assert await client.get("env", "count") == "0"


async def test_find_answers_markers_nearest_first() -> None:
    model = EnvironmentModel()
    async with serve(model, name="env") as client:
        for i, (kind, x) in enumerate([("box", 0.0), ("box", 3.0), ("ball", 3.2), ("box", 6.0)]):
            marker = f"<marker><id>m{i}</id><class>{kind}</class><location>({x} 0)</location></marker>"
            await client.set("env", "observe", marker)
        one = await client.get("env", "find", **{"class": "box", "near": "(3.4 0)", "count": "1"})
        assert [m.get("id") for m in parse_marker_list(one)] == ["m1"]
        two = await client.get("env", "find", kind="box", near="(5 0)", count="2")
        assert [m.split("</id>")[0] for m in two.split("<id>")[1:]] == ["m3", "m1"]
        inside = await client.get("env", "find", area="(2 -1 4 1)")
        assert sorted(m.split("</id>")[0] for m in inside.split("<id>")[1:]) == ["m1", "m2"]
        # "The nearest red marker": a field of the sightings, here color.
        await client.set(
            "env",
            "observe",
            "<marker><class>box</class><location>(9 0)</location><color>(1 0 0)</color></marker>",
        )
        red = await client.get("env", "find", near="(0 0)", where="color=(1 0 0)", count="1")
        assert [m.get("location") for m in parse_marker_list(red)] == ["(9 0 0)"]
        assert await client.get("env", "find", where="color=(0 0 1)") == "()"
        with pytest.raises(InvalidArgumentError, match="where is field=value pairs"):
            await client.get("env", "find", where="color")
        with pytest.raises(InvalidArgumentError, match="near is"):
            await client.get("env", "find", near="(1 2 3)")
        with pytest.raises(InvalidArgumentError, match="count must be from 1 to 100"):
            await client.get("env", "find", count="1000")
        with pytest.raises(InvalidArgumentError, match="needs a location"):
            await client.set("env", "observe", "<marker><class>box</class></marker>")


async def test_grid_properties_and_clear(client_model: tuple[AsyncClient, EnvironmentModel]) -> None:
    client, model = client_model
    assert parse_list(await client.get("env", "grid")) == ["temperature", "occupancy"]
    model.record("temperature", 0.25, 0.25, 20.0)
    model.record("temperature", 0.25, 0.25, 21.0)
    info = dict(parse_list(await client.get("env", "grid.temperature.info")))
    assert info["filled"] == "1" and info["total"] == "2" and info["min"] == "20.5"
    await client.set("env", "observe", "<marker><location>(0.3 0.3)</location></marker>")
    occupancy = np.load(io.BytesIO(model.layer_npy("occupancy")))
    assert occupancy.sum() == 1.0
    assert Image.open(io.BytesIO(model.layer_png("temperature"))).format == "PNG"
    await client.set("env", "clear", "")
    assert await client.get("env", "count") == "0"
    assert dict(parse_list(await client.get("env", "grid.temperature.info")))["filled"] == "0"


@pytest.fixture
async def client_model():
    model = EnvironmentModel(grid={"origin": [0, 0], "cell": 0.5, "shape": [4, 4]})
    async with serve(model, name="env") as client:
        yield client, model


async def test_a_layer_is_binary_npy_with_its_media_type_and_listeners() -> None:
    model = EnvironmentModel(grid={"origin": [0, 0], "cell": 1.0, "shape": [2, 2]})
    backend = serve_backend(model)
    await backend.start()
    try:
        heard: list[Change] = []
        sub = await backend.listen("grid.temperature", heard.append)
        model.record("temperature", 1.5, 0.5, 25.0)
        await wait_until(lambda: bool(heard), what="the layer's listener hears of the reading")
        assert heard[0].path == "grid.temperature"
        value = await backend.get("grid.temperature")
        assert isinstance(value, bytes) and value == heard[-1].value
        array = np.load(io.BytesIO(value), allow_pickle=False)
        assert array.dtype == np.float32 and array[0, 1] == 25.0 and np.isnan(array[1, 1])
        await sub.close()
        assert await backend.get("grid.temperature.media_type") == "application/x-npy"
        assert await backend.get("grid.temperature.gui") == "bytes"
        assert await backend.get("grid.temperature.image.media_type") == "image/png"
        png = await backend.get("grid.temperature.image")
        assert isinstance(png, bytes) and png.startswith(b"\x89PNG\r\n\x1a\n")
        described = {p.name: p for p in (await backend.describe()).properties}
        layer = described["grid.temperature"]
        assert (layer.type, layer.media_type) == ("bytes", "application/x-npy")
        assert (described["grid.occupancy.image"].type, described["grid.occupancy.image"].media_type) == (
            "bytes",
            "image/png",
        )
    finally:
        await backend.aclose()


def test_marker_lists_in_every_form_a_camera_may_send() -> None:
    one = "<marker><id>a</id><class>box</class><location>(1 2)</location></marker>"
    two = "<marker><id>b</id><class>ball</class><location>(3 4 0.5)</location></marker>"
    for text in (f"({one} {two})", f"{one} {two}", f"<markers>{one}{two}</markers>", f"  ( {one}\n{two} )  "):
        assert [m.get("id") for m in parse_marker_list(text)] == ["a", "b"], text
    assert parse_marker_list("()") == [] and parse_marker_list("") == []
    assert write_marker_list(parse_marker_list(f"{one} {two}")) == f"({one} {two})"
    with pytest.raises(InvalidArgument, match="holds something else"):
        parse_marker_list(f"({one} stray words)")
    with pytest.raises(InvalidArgument, match="the limit is 1000"):
        parse_marker_list("(" + " ".join([one] * 1001) + ")")
    with pytest.raises(InvalidArgument, match="a marker of the list is bad"):
        parse_marker_list("(<marker><id>a</id><id>b</id></marker>)")


async def test_markers_and_grid_are_typed_values_a_wildcard_get_reads(
    client_model: tuple[AsyncClient, EnvironmentModel],
) -> None:
    client, _ = client_model
    for seen in (
        "<marker><id>crate</id><class>box</class><location>(1 1)</location></marker>",
        "<marker><id>ball</id><class>ball</class><location>(1.5 0.5)</location></marker>",
    ):
        await client.set("env", "observe", seen)
    described = {p.name: p for p in (await client.describe("env")).properties}
    assert (described["markers"].type, described["grid"].type) == ("names", "names")
    assert described["markers.crate"].type == "marker"
    found = await client.get_matching("env", "markers.*")
    assert sorted(found) == ["markers.ball", "markers.crate"]
    crate = found["markers.crate"]
    assert isinstance(crate, str) and parse_marker(crate).get("class") == "box"
