"""Actions and queries (reads never act) and the typed model a LocalService describes."""

from __future__ import annotations

from typing import Annotated

import numpy as np
import pytest

from services.kernel.backend import Change
from services.kernel.core import LocalService, Prop, Resource, action, functional, query, read_write
from services.kernel.errors import Code, InvalidArgument, PropertyError
from services.kernel.model import Access, ParameterModel
from services.kernel.values import Marker, Vector
from tests.support.fake_backend import DictBackend


class Wheels(Resource):
    """The drive."""

    speed: Annotated[float, Prop(minimum=0.0, maximum=2.0, unit="m/s", doc="top speed")] = 1.0
    mode: Annotated[str, Prop(choices=("eco", "sport"))] = "eco"
    pose: Annotated[Vector, Prop(readonly=True, length=6, unit="m", minimum=-10.0, maximum=10.0)]

    def __init__(self) -> None:
        self.pose = np.zeros(6)
        self.stops = 0

    @action(doc="stop now")
    def halt(self) -> None:
        self.stops += 1

    @functional
    def legacy(self) -> str:
        self.stops += 1
        return "stopped"


class Rover(Resource):
    """A rover."""

    resource_type = "rover"
    wheels: Wheels
    battery: Annotated[float, Prop(readonly=True, unit="1", minimum=0.0, maximum=1.0)] = 1.0

    def __init__(self, remote: DictBackend) -> None:
        self.wheels = Wheels()
        self.arm = remote

    @action(unit="m")
    def blink(self, times: int, *, period: float = 0.5) -> str:
        return f"{times}x{period:g}"

    @action
    def goto(self, target: Marker) -> None:
        """Drive to the target."""

    @query(doc="names nearby")
    def nearby(self, kind: str = "", *, radius: float = 1.0) -> list[str]:
        return [kind, f"{radius:g}"]


@pytest.fixture
def rover() -> Rover:
    return Rover(DictBackend({"joint": "0.5"}))


@pytest.fixture
def svc(rover: Rover) -> LocalService:
    return LocalService(rover)


async def test_get_never_invokes_an_action(svc: LocalService, rover: Rover) -> None:
    for path in ("wheels.halt", "wheels.legacy"):
        with pytest.raises(PropertyError) as info:
            await svc.get(path)
        assert info.value.code is Code.FAILED_PRECONDITION
        assert info.value.message == f"`{path}` is an action: Set it to invoke it"
    assert rover.wheels.stops == 0


async def test_listen_named_exactly_on_an_action_is_failed_precondition(
    svc: LocalService, rover: Rover
) -> None:
    heard: list[Change] = []
    with pytest.raises(PropertyError) as info:
        await svc.listen("wheels.halt", heard.append)
    assert info.value.code is Code.FAILED_PRECONDITION
    assert "Set it to invoke it" in info.value.message
    assert rover.wheels.stops == 0


async def test_set_with_a_value_on_an_action_that_takes_none_is_invalid(
    svc: LocalService, rover: Rover
) -> None:
    with pytest.raises(InvalidArgument, match="takes no value"):
        await svc.set("wheels.halt", "garbage")
    assert rover.wheels.stops == 0
    assert await svc.set("wheels.halt", "") == ""
    assert rover.wheels.stops == 1


async def test_set_with_a_value_of_the_wrong_type_is_invalid(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="bad value for `blink`"):
        await svc.set("blink", "often")
    assert await svc.set("blink", "3", {"period": "0.25"}) == "3x0.25"


async def test_a_query_answers_a_get_and_refuses_a_set(svc: LocalService) -> None:
    assert await svc.get("nearby", {"kind": "robot", "radius": "2"}) == "(robot 2)"
    with pytest.raises(PropertyError) as info:
        await svc.set("nearby", "garbage")
    assert info.value.code is Code.FAILED_PRECONDITION
    assert "query" in info.value.message


async def test_a_query_needs_defaults_for_every_parameter() -> None:
    class Bad(Resource):
        @query
        def find(self, kind: str) -> list[str]:
            return [kind]

    with pytest.raises(TypeError, match="a query takes request parameters only"):
        LocalService(Bad())


async def test_ranges_hold_for_each_element_and_choices_are_enforced(svc: LocalService) -> None:
    with pytest.raises(InvalidArgument, match="out of range"):
        await svc.set("wheels.speed", "3")
    with pytest.raises(InvalidArgument, match="eco, sport"):
        await svc.set("wheels.mode", "turbo")
    assert await svc.set("wheels.mode", "sport") == "sport"


async def test_describe_returns_the_whole_tree_with_types_and_metadata(svc: LocalService) -> None:
    model = await svc.describe()
    assert model.type == "rover"
    assert model.doc == "A rover."
    by_name = {p.name: p for p in model.properties}
    assert list(by_name) == await svc.properties()
    speed = by_name["wheels.speed"]
    assert (speed.type, speed.access, speed.unit, speed.minimum, speed.maximum) == (
        "number",
        Access.READ_WRITE,
        "m/s",
        0.0,
        2.0,
    )
    assert speed.doc == "top speed"
    assert by_name["wheels.mode"].choices == ("eco", "sport")
    pose = by_name["wheels.pose"]
    assert (pose.type, pose.access, pose.length, pose.unit) == ("vector", Access.READ, 6, "m")
    assert by_name["wheels"].type == "namespace"
    halt = by_name["wheels.halt"]
    assert (halt.access, halt.value, halt.type, halt.gui) == (Access.ACTION, None, "none", "button")
    assert by_name["wheels.legacy"].access is Access.ACTION
    blink = by_name["blink"]
    assert blink.value == ParameterModel("times", "integer", required=True)
    assert blink.parameters == (ParameterModel("period", "number", required=False, default="0.5"),)
    assert blink.type == "text" and blink.unit == "m"
    assert by_name["goto"].value == ParameterModel("target", "marker")
    assert by_name["goto"].doc == "Drive to the target."
    nearby = by_name["nearby"]
    assert (nearby.access, nearby.type, nearby.value) == (Access.QUERY, "names", None)
    assert [p.name for p in nearby.parameters] == ["kind", "radius"]
    # A Backend child answers through its own describe(), under its name.
    assert by_name["arm.joint"].access is Access.UNKNOWN
    assert by_name["arm"].type == "namespace"


async def test_metadata_sub_properties_still_answer(svc: LocalService) -> None:
    assert await svc.get("wheels.speed.doc") == "top speed"
    assert await svc.get("wheels.halt.gui") == "button"
    assert await svc.get("blink.parameters") == "((period number 0.5))"


class Crowd(Resource):
    """Many robots behind one property."""

    def __init__(self) -> None:
        self.commanded: list[str] = []

    @read_write(unit="m/s", doc="mean speed; a Set commands everyone")
    async def pace(self, value: float | None = None, /) -> float | str:
        if value is None:
            return 0.5  # reads never act: nothing is commanded
        self.commanded.append(f"{value:g}")
        return "ok"


async def test_a_read_write_method_reads_without_acting_and_a_set_needs_a_value() -> None:
    crowd = Crowd()
    service = LocalService(crowd)
    assert await service.get("pace") == "0.5"
    assert crowd.commanded == []
    assert await service.set("pace", "2") == "ok"
    assert crowd.commanded == ["2"]
    with pytest.raises(InvalidArgument, match="needs a value"):
        await service.set("pace", "")
    (pace,) = [p for p in (await service.describe()).properties if p.name == "pace"]
    assert (pace.access, pace.type, pace.unit) == (Access.READ_WRITE, "number", "m/s")


def test_a_read_write_method_whose_value_a_get_could_carry_is_refused() -> None:
    class Bad(Resource):
        @read_write
        def pace(self, value: float | None = None) -> float:  # not positional-only
            return 0.0

    with pytest.raises(TypeError, match="positional-only with the default None"):
        LocalService(Bad())
