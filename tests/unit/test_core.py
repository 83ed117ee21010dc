"""The class wrapper used as a service author uses it: Get and Set through LocalService."""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pytest

from services.kernel.core import LocalService, Prop, Resource, functional, query
from services.kernel.errors import Code, InvalidArgument, NotFound, PropertyError
from services.kernel.values import Marker, Vector, parse_list, parse_marker, parse_names


class Gripper(Resource):
    """A two-finger gripper."""

    opening: Annotated[float, Prop(minimum=0.0, maximum=0.1, doc="finger gap, m")] = 0.05
    closed: Annotated[bool, Prop(readonly=True)] = False

    @functional(gui="button", doc="close the fingers")
    def grip(self, force: float = 1.0) -> str:
        self.closed = True
        return f"gripped-{force:g}"


class Arm(Resource):
    """An arm with a gripper, used throughout these tests."""

    resource_type = "arm"

    location: Annotated[Vector, Prop(readonly=True, gui="pose", doc="where the arm stands")]
    joints: Vector
    name: str = "arm1"
    count: int = 0
    target: Marker
    gripper: Gripper

    def __init__(self) -> None:
        self.location = np.array([1.0, 2.0, 0.0, 0.0, 0.0, 0.5])
        self.joints = np.zeros(3)
        self.target = parse_marker("<marker><location>(1 2)</location><color>red</color></marker>")
        self.gripper = Gripper()
        self.calls: list[tuple[object, ...]] = []
        self._temperature = 30.0

    @property
    def temperature(self) -> float:
        """Motor temperature, degrees Celsius."""
        return self._temperature

    @functional
    def moveto(self, target: Marker, *, frame: str = "world", slow: bool = False) -> None:
        """Move the tool to the target."""
        self.calls.append(
            ("moveto", target.location.tolist() if target.location is not None else None, frame, slow)
        )

    @functional
    async def home(self) -> str:
        self.calls.append(("home",))
        return "homed"

    @query
    def find(self, kind: str = "", *, near: Vector | None = None, radius: float = 1.0) -> list[str]:
        self.calls.append(("find", kind, None if near is None else near.tolist(), radius))
        return ["a", "b"] if kind else []

    @functional
    def reset(self, *, hard: bool) -> None:
        self.calls.append(("reset", hard))

    def helper(self) -> None:
        """A plain method: not a property."""


@pytest.fixture
def arm() -> Arm:
    return Arm()


@pytest.fixture
def svc(arm: Arm) -> LocalService:
    return LocalService(arm, url="local")


async def test_info_names_the_resource_type(svc: LocalService) -> None:
    assert svc.info.type == "arm"
    assert svc.info.url == "local"


async def test_get_attributes_as_text(svc: LocalService) -> None:
    assert await svc.get("location") == "(1 2 0 0 0 0.5)"
    assert await svc.get("name") == "arm1"
    assert await svc.get("count") == "0"
    assert await svc.get("temperature") == "30"
    assert await svc.get("gripper.opening") == "0.05"
    assert await svc.get("gripper.closed") == "false"


async def test_vector_elements_by_axis_or_index(svc: LocalService) -> None:
    assert await svc.get("location.y") == "2"
    assert await svc.get("location.yaw") == "0.5"
    assert await svc.get("location.0") == "1"


async def test_marker_fields_are_sub_properties(svc: LocalService) -> None:
    assert await svc.get("target.location") == "(1 2)"
    assert await svc.get("target.color") == "red"
    with pytest.raises(NotFound):
        await svc.get("target.size")


async def test_set_parses_by_annotation_and_returns_the_new_value(svc: LocalService, arm: Arm) -> None:
    assert await svc.set("joints", "(0.1 0.2 0.3)") == "(0.1 0.2 0.3)"
    assert arm.joints.tolist() == [0.1, 0.2, 0.3]
    assert await svc.set("count", "7") == "7"
    assert arm.count == 7
    assert await svc.set("name", "left arm") == "left arm"
    assert await svc.set("target", "<marker><location>(5 6)</location></marker>") == (
        "<marker><location>(5 6)</location></marker>"
    )
    assert await svc.get("target.location") == "(5 6)"


async def test_set_one_vector_element(svc: LocalService, arm: Arm) -> None:
    assert await svc.set("joints.1", "0.7") == "0.7"
    assert arm.joints.tolist() == [0.0, 0.7, 0.0]


async def test_set_read_only_is_failed_precondition(svc: LocalService) -> None:
    for path, value in [
        ("location", "(0 0)"),
        ("location.x", "3"),
        ("temperature", "1"),
        ("gripper.closed", "1"),
    ]:
        with pytest.raises(PropertyError) as info:
            await svc.set(path, value)
        assert info.value.code is Code.FAILED_PRECONDITION
        assert f"`{path}`" in info.value.message


async def test_bad_values_are_invalid_argument(svc: LocalService, arm: Arm) -> None:
    with pytest.raises(InvalidArgument, match="`joints`"):
        await svc.set("joints", "(1 two 3)")
    with pytest.raises(InvalidArgument):
        await svc.set("count", "1.5")
    with pytest.raises(InvalidArgument):
        await svc.set("target", "<marker><location>(1 2)</marker>")
    assert arm.joints.tolist() == [0.0, 0.0, 0.0]


async def test_range_of_a_number_is_checked(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="out of range"):
        await svc.set("gripper.opening", "0.5")
    assert await svc.set("gripper.opening", "0.02") == "0.02"


async def test_unknown_property_is_not_found_with_a_suggestion(svc: LocalService) -> None:
    with pytest.raises(NotFound, match="did you mean `location`"):
        await svc.get("locaton")
    with pytest.raises(NotFound, match=r"`gripper\.openin`"):
        await svc.get("gripper.openin")
    with pytest.raises(NotFound):
        await svc.get("location.w")
    with pytest.raises(NotFound):
        await svc.get("name.x")
    with pytest.raises(NotFound):
        await svc.get("helper")
    with pytest.raises(NotFound):
        await svc.get("calls")


async def test_bad_path_syntax_is_invalid_argument(svc: LocalService) -> None:
    for path in ["", "location..x", "location x", "robots.*"]:
        with pytest.raises(InvalidArgument):
            await svc.get(path)


async def test_functional_set_passes_value_and_parameters(svc: LocalService, arm: Arm) -> None:
    answer = await svc.set(
        "moveto", "<marker><location>(3 4)</location></marker>", {"frame": "robot", "slow": "true"}
    )
    assert answer == ""
    assert arm.calls == [("moveto", [3.0, 4.0], "robot", True)]


async def test_functional_unknown_parameter_names_the_accepted_ones(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument) as info:
        await svc.set("moveto", "<marker><location>(3 4)</location></marker>", {"speed": "1"})
    assert "`speed`" in info.value.message
    assert "`frame`" in info.value.message and "`slow`" in info.value.message


async def test_functional_bad_parameter_value(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="`slow`"):
        await svc.set("moveto", "<marker><location>(3 4)</location></marker>", {"slow": "maybe"})


async def test_functional_missing_required_parameter(svc: LocalService, arm: Arm) -> None:
    with pytest.raises(InvalidArgument, match="`hard`"):
        await svc.set("reset", "")
    await svc.set("reset", "", {"hard": "yes"})
    assert arm.calls == [("reset", True)]


async def test_get_on_an_action_is_failed_precondition(svc: LocalService) -> None:
    with pytest.raises(PropertyError) as info:
        await svc.get("moveto")
    assert info.value.code is Code.FAILED_PRECONDITION
    assert info.value.message == "`moveto` is an action: Set it to invoke it"


async def test_get_calls_a_query_with_its_parameters(svc: LocalService, arm: Arm) -> None:
    assert await svc.get("find", {"kind": "robot", "near": "(1 2)", "radius": "2.5"}) == "(a b)"
    assert await svc.get("find") == "()"
    assert arm.calls == [("find", "robot", [1.0, 2.0], 2.5), ("find", "", None, 1.0)]


async def test_async_functional_is_awaited(svc: LocalService, arm: Arm) -> None:
    assert await svc.set("home", "") == "homed"
    assert await svc.set("home", "") == "homed"
    assert arm.calls == [("home",), ("home",)]


async def test_functional_in_a_child(svc: LocalService, arm: Arm) -> None:
    assert await svc.set("gripper.grip", "", {}) == "gripped-1"
    assert await svc.set("gripper.grip", "2.5") == "gripped-2.5"
    assert arm.gripper.closed is True


async def test_attributes_take_no_parameters(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="no parameters"):
        await svc.get("location", {"frame": "robot"})


async def test_parameters_metadata(svc: LocalService) -> None:
    assert parse_list(await svc.get("moveto.parameters")) == [
        ["frame", "text", "world"],
        ["slow", "boolean", "false"],
    ]
    assert parse_list(await svc.get("reset.parameters")) == [["hard", "boolean", "-"]]
    assert parse_list(await svc.get("find.parameters")) == [
        ["kind", "text", []],
        ["near", "vector", []],
        ["radius", "number", "1"],
    ]
    assert await svc.get("location.parameters") == "()"
    assert await svc.get("gripper.parameters") == "()"


async def test_gui_metadata(svc: LocalService) -> None:
    assert await svc.get("location.gui") == "pose"
    assert await svc.get("joints.gui") == "vector"
    assert await svc.get("count.gui") == "number"
    assert await svc.get("name.gui") == "text"
    assert await svc.get("target.gui") == "marker"
    assert await svc.get("gripper.closed.gui") == "switch"
    assert await svc.get("moveto.gui") == "button"
    assert await svc.get("gripper.gui") == "group"


async def test_doc_metadata(svc: LocalService) -> None:
    assert await svc.get("location.doc") == "where the arm stands"
    assert await svc.get("temperature.doc") == "Motor temperature, degrees Celsius."
    assert await svc.get("moveto.doc") == "Move the tool to the target."
    assert await svc.get("gripper.grip.doc") == "close the fingers"
    assert await svc.get("gripper.doc") == "A two-finger gripper."


async def test_metadata_is_read_only(svc: LocalService) -> None:
    with pytest.raises(PropertyError) as info:
        await svc.set("location.gui", "slider")
    assert info.value.code is Code.FAILED_PRECONDITION


async def test_properties_lists_every_path_depth_first(svc: LocalService) -> None:
    expected = [
        "location",
        "joints",
        "name",
        "count",
        "target",
        "gripper",
        "gripper.opening",
        "gripper.closed",
        "gripper.grip",
        "temperature",
        "moveto",
        "home",
        "find",
        "reset",
    ]
    assert parse_names(await svc.get("properties")) == expected
    assert await svc.properties() == expected


async def test_namespace_value_is_its_names(svc: LocalService) -> None:
    assert await svc.get("gripper") == "(opening closed grip)"
    with pytest.raises(PropertyError) as info:
        await svc.set("gripper", "x")
    assert info.value.code is Code.FAILED_PRECONDITION


async def test_namespace_with_a_value_of_its_own() -> None:
    class Entry(Resource):
        url: str = "tcp://10.0.0.7:7000"

        def _value(self) -> str:
            return self.url

    class Root(Resource):
        def __init__(self) -> None:
            self.scout = Entry()

    svc = LocalService(Root())
    assert await svc.get("scout") == "tcp://10.0.0.7:7000"
    assert await svc.get("scout.url") == "tcp://10.0.0.7:7000"
    assert await svc.get("properties") == "(scout scout.url)"


async def test_hot_path_get_is_stable_over_many_calls(svc: LocalService, arm: Arm) -> None:
    for i in range(2000):
        arm.count = i
        assert await svc.get("count") == str(i)


def test_reserved_names_are_refused() -> None:
    class Bad(Resource):
        properties: str = "x"

    with pytest.raises(TypeError, match="reserved"):
        LocalService(Bad())
