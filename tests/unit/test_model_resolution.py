"""A property's resolution (the smallest step its value is known to) from the class to every wire.

A client shows as many decimals as the resolution implies (the console: docs/console.md, "Widgets
that fit the data"); a service declares it with ``Prop(resolution=0.01)``.
"""

from __future__ import annotations

import math
from typing import Annotated

import numpy as np
import pytest

from gateway.fronts.http.api import property_json
from services.kernel.core import LocalService, Prop, Resource
from services.kernel.model import Access, PropertyModel, ServiceModel
from services.kernel.model_codec import model_from_proto, model_from_text, model_to_proto, model_to_text
from services.kernel.values import Vector


class Rover(Resource):
    """A rover whose location is known to the centimetre."""

    resource_type = "rover"

    location: Annotated[Vector, Prop(readonly=True, unit="m", length=2, resolution=0.01)]
    speed: Annotated[float, Prop(minimum=0.0, maximum=2.0, unit="m/s", resolution=0.05)] = 0.0
    name: Annotated[str, Prop(doc="no resolution: a text")] = "r"

    def __init__(self) -> None:
        self.location = np.zeros(2)


async def test_a_declared_resolution_is_in_the_model_and_an_undeclared_one_is_absent() -> None:
    model = {p.name: p for p in (await LocalService(Rover()).describe()).properties}
    assert (model["location"].resolution, model["speed"].resolution, model["name"].resolution) == (
        0.01,
        0.05,
        None,
    )


def test_the_resolution_crosses_the_grpc_model_the_line_form_and_the_http_json() -> None:
    model = ServiceModel(
        type="rover",
        properties=(
            PropertyModel("location", "vector", Access.READ, length=2, unit="m", resolution=0.01),
            PropertyModel("name", "text", Access.READ_WRITE),
        ),
    )
    assert model_to_proto(model).properties[0].resolution == 0.01
    assert not model_to_proto(model).properties[1].HasField("resolution")
    assert model_from_proto(model_to_proto(model)) == model
    assert "(resolution 0.01)" in model_to_text(model)
    assert model_from_text(model_to_text(model), "rover") == model
    assert property_json(model.properties[0])["resolution"] == 0.01
    assert property_json(model.properties[1])["resolution"] is None


def test_a_line_device_resolution_that_is_not_a_positive_number_is_skipped_like_an_unknown_tag() -> None:
    for bad in ("0", "-1", "fast"):
        read = model_from_text(f"((x number read (m) - - (a doc) (resolution {bad})))", "d")
        assert read.properties[0].resolution is None
        assert read.properties[0].unit == "m"


@pytest.mark.parametrize(
    ("annotation", "why"),
    [
        (Annotated[float, Prop(resolution=0)], "positive number"),
        (Annotated[float, Prop(resolution=-0.1)], "positive number"),
        (Annotated[float, Prop(resolution=math.nan)], "positive number"),
        (Annotated[float, Prop(resolution=True)], "positive number"),
        (Annotated[str, Prop(resolution=0.1)], "number or a vector, not text"),
    ],
    ids=["zero", "negative", "nan", "boolean", "on-a-text"],
)
def test_a_resolution_that_means_nothing_is_refused_with_the_class(annotation: object, why: str) -> None:
    with pytest.raises(TypeError, match=why):
        LocalService(type("Bad", (Resource,), {"__annotations__": {"x": annotation}, "x": None})())
