"""The line form of a service's model (docs/device-spec.md §9, docs/line-protocol.md §12): what a
device answers to ``GET properties.model``, with and without the tagged lists that carry widgets
and parameters."""

from __future__ import annotations

import dataclasses

import pytest

from services.kernel.errors import InvalidArgument
from services.kernel.model import Access, ParameterModel, PropertyModel, ServiceModel
from services.kernel.model_codec import model_from_text, model_to_text

MOVETO = PropertyModel(
    name="behaviors.moveto",
    type="none",
    access=Access.ACTION,
    doc="drive to the target",
    gui="button",
    value=ParameterModel(name="target", type="marker", doc="where to"),
    parameters=(
        ParameterModel(name="frame", type="text", required=False, default="world"),
        ParameterModel(name="offset", type="vector", required=False, default="(0 0.5)", doc="from it"),
    ),
)
MODEL = ServiceModel(
    type="mobile_robot",
    properties=(
        PropertyModel(
            name="location", type="vector", access=Access.READ, length=6, unit="m, rad", gui="pose"
        ),
        PropertyModel(
            name="speed",
            type="number",
            access=Access.READ_WRITE,
            unit="m/s",
            minimum=0,
            maximum=2,
            gui="slider",
        ),
        PropertyModel(name="mode", type="text", access=Access.READ_WRITE, choices=("auto", "manual")),
        MOVETO,
    ),
)


def test_the_model_travels_whole() -> None:
    text = model_to_text(MODEL)
    assert model_from_text(text, "mobile_robot") == MODEL
    assert "(gui pose)" in text and "(param frame text optional (world) ())" in text
    assert "(param offset vector optional ((0 0.5)) (from it))" in text


def test_without_docs_everything_else_travels() -> None:
    back = {p.name: p for p in model_from_text(model_to_text(MODEL, docs=False), "mobile_robot").properties}
    moveto = back["behaviors.moveto"]
    assert moveto.doc == "" and moveto.gui == "button"
    assert moveto.value == ParameterModel(name="target", type="marker")
    assert [(q.name, q.default) for q in moveto.parameters] == [("frame", "world"), ("offset", "(0 0.5)")]
    assert back["location"].length == 6 and back["mode"].choices == ("auto", "manual")


def test_the_hints_are_left_out_before_what_a_set_or_a_call_needs() -> None:
    resolved = ServiceModel(
        type="mobile_robot",
        properties=(dataclasses.replace(MODEL.properties[0], resolution=0.01), *MODEL.properties[1:]),
    )
    assert "(resolution 0.01)" in model_to_text(resolved, docs=False)
    without_resolution = model_to_text(resolved, docs=False, hints=("gui",))
    assert "resolution" not in without_resolution and "(gui pose)" in without_resolution
    bare = model_to_text(resolved, docs=False, hints=())
    assert "resolution" not in bare and "gui" not in bare
    moveto = {p.name: p for p in model_from_text(bare, "mobile_robot").properties}["behaviors.moveto"]
    assert moveto.value == ParameterModel(name="target", type="marker")
    assert [q.name for q in moveto.parameters] == ["frame", "offset"]


def test_without_tags_it_is_the_first_form() -> None:
    text = model_to_text(MODEL, docs=False, tags=False)
    assert "gui" not in text and "param" not in text
    assert text.startswith("((location vector read (m, rad) - -) (speed number read-write (m/s) 0 2)")


def test_the_first_form_still_parses() -> None:
    """A device that answers the seven-field form (the C library's) is read as before."""
    text = (
        "((led boolean read-write () - - (status light))"
        " (temp number read (degC) -40 125 (board temperature))"
        " (reset none action () - - (restart the board)) (note text read))"
    )
    props = {p.name: p for p in model_from_text(text, "board").properties}
    assert props["temp"] == PropertyModel(
        name="temp",
        type="number",
        access=Access.READ,
        unit="degC",
        minimum=-40,
        maximum=125,
        doc="board temperature",
    )
    assert (
        props["reset"].access is Access.ACTION and props["reset"].gui == "" and props["reset"].value is None
    )
    assert props["note"] == PropertyModel(name="note", type="text", access=Access.READ)


def test_tags_a_reader_does_not_know_are_skipped() -> None:
    text = "((speed number read-write (m/s) 0 2 () (gui slider) (colour red) (step 0.1) odd (param)))"
    (speed,) = model_from_text(text, "robot").properties
    assert speed.gui == "slider" and speed.parameters == () and speed.maximum == 2


def test_a_bad_entry_is_refused() -> None:
    with pytest.raises(InvalidArgument, match="model entry 1"):
        model_from_text("((speed number))", "robot")
