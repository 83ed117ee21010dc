"""An annotation that does not resolve is a clear error when the class is first served, never ``Any``."""

from __future__ import annotations

import pytest

from services.kernel.core import LocalService, Resource, functional


def test_an_attribute_annotation_that_does_not_resolve_names_class_member_and_annotation() -> None:
    class Lamp(Resource):
        brightness: Lumens  # type: ignore[name-defined]  # noqa: F821

    with pytest.raises(TypeError) as info:
        LocalService(Lamp())
    message = str(info.value)
    assert "Lamp.brightness" in message
    assert "'Lumens'" in message


def test_a_parameter_annotation_that_does_not_resolve_names_the_method_and_parameter() -> None:
    class Arm(Resource):
        @functional
        def grip(self, force: Newtons) -> None:  # type: ignore[name-defined]  # noqa: F821
            """Close the gripper."""

    with pytest.raises(TypeError) as info:
        LocalService(Arm())
    message = str(info.value)
    assert "Arm.grip" in message
    assert "force" in message
    assert "'Newtons'" in message


async def test_a_private_annotation_is_never_a_member_and_need_not_resolve() -> None:
    class Counter(Resource):
        count: int
        _helper: Undefined  # type: ignore[name-defined]  # noqa: F821

        def __init__(self) -> None:
            self.count = 3

    svc = LocalService(Counter())
    assert await svc.properties() == ["count"]
    assert await svc.get("count") == "3"
