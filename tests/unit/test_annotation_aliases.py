"""Numpy array annotations in every form numpy produces, and type aliases, read as the types they name.

numpy < 2.5 spells ``NDArray[np.float64]`` as ``np.ndarray[shape, np.dtype[float64]]``;
numpy >= 2.5 makes ``NDArray`` a ``TypeAliasType``, so ``NDArray[np.float64]``
is a subscripted alias whose origin is the alias, not ``np.ndarray``. Both
forms are built here whatever numpy is installed, so each is covered on every
interpreter.
"""

from __future__ import annotations

import sys
import typing
from typing import Annotated, Any, Optional

import numpy as np
import numpy.typing as npt
import pytest

from services.kernel.core import LocalService, Prop, Resource
from services.kernel.values import Vector, parse_as, type_name

if sys.version_info >= (3, 12):
    from typing import TypeAliasType
else:
    from typing_extensions import TypeAliasType

ScalarT = typing.TypeVar("ScalarT", bound=np.generic)

# The shape of numpy >= 2.5's NDArray: a generic alias of np.ndarray, subscripted by the scalar type.
NDArrayAlias = TypeAliasType(
    "NDArrayAlias", np.ndarray[tuple[Any, ...], np.dtype[ScalarT]], type_params=(ScalarT,)
)
Pose = TypeAliasType("Pose", npt.NDArray[np.float64])
PoseOfAlias = TypeAliasType("PoseOfAlias", NDArrayAlias[np.float64])
Speed = TypeAliasType("Speed", float)
Names = TypeAliasType("Names", list[str])

VECTOR_FORMS = [
    pytest.param(np.ndarray, id="ndarray"),
    pytest.param(np.ndarray[Any, Any], id="ndarray[Any, Any]"),
    pytest.param(np.ndarray[tuple[int], np.dtype[np.float64]], id="ndarray[shape, dtype]"),
    pytest.param(npt.NDArray[np.float64], id="installed NDArray[float64]"),
    pytest.param(npt.NDArray[Any], id="installed NDArray[Any]"),
    pytest.param(npt.NDArray, id="installed NDArray"),
    pytest.param(Vector, id="services.kernel.values.Vector"),
    pytest.param(NDArrayAlias[np.float64], id="numpy>=2.5 NDArray[float64]"),
    pytest.param(NDArrayAlias, id="numpy>=2.5 NDArray"),
    pytest.param(Pose, id="alias of NDArray[float64]"),
    pytest.param(PoseOfAlias, id="alias of a subscripted alias"),
]


def test_the_installed_numpy_spells_ndarray_in_a_known_form() -> None:
    # A third form in a future numpy fails here first, naming it, rather than in a robot's constructor.
    origin = typing.get_origin(npt.NDArray[np.float64])
    assert origin is np.ndarray or isinstance(origin, TypeAliasType | getattr(typing, "TypeAliasType", ()))


@pytest.mark.parametrize("tp", VECTOR_FORMS)
def test_every_numpy_array_form_is_a_vector(tp: Any) -> None:
    assert type_name(tp) == "vector"
    assert parse_as(tp, "(1 2.5)").tolist() == [1.0, 2.5]


@pytest.mark.parametrize("tp", VECTOR_FORMS)
def test_lists_and_optionals_of_every_numpy_array_form(tp: Any) -> None:
    assert type_name(list[tp]) == "vectors"
    assert [v.tolist() for v in parse_as(list[tp], "((1) (2 3))")] == [[1.0], [2.0, 3.0]]
    assert type_name(Optional[tp]) == "vector"  # noqa: UP045
    assert parse_as(Optional[tp], "") is None  # noqa: UP045
    assert type_name(Annotated[tp, "doc"]) == "vector"


def test_aliases_of_other_value_types_read_as_what_they_name() -> None:
    assert type_name(Speed) == "number"
    assert parse_as(Speed, "0.5") == 0.5
    assert type_name(Names) == "names"
    assert parse_as(Names, "(a b)") == ["a", "b"]
    assert parse_as(list[Speed], "(1 2)") == [1.0, 2.0]


@pytest.mark.skipif(sys.version_info < (3, 12), reason="an alias cycle needs the lazy `type` statement")
def test_an_alias_that_never_ends_is_a_type_error_not_a_hang() -> None:
    # The `type` statement is run from text: the source must still parse on Python 3.11.
    namespace: dict[str, Any] = {}
    exec("type Ping = Pong\ntype Pong = Ping\ntype Nested = list[Nested]", namespace)
    with pytest.raises(TypeError, match="does not end"):
        type_name(namespace["Ping"])
    with pytest.raises(TypeError, match="does not end"):
        parse_as(namespace["Pong"], "1")
    with pytest.raises(TypeError, match="unsupported list item"):
        parse_as(namespace["Nested"], "(a)")


async def test_a_resource_with_an_aliased_numpy_attribute_is_served_as_a_vector() -> None:
    class Rover(Resource):
        location: Annotated[NDArrayAlias[np.float64], Prop(doc="x y (m)")]
        heading: Pose

        def __init__(self) -> None:
            self.location = np.array([1.0, 2.0])
            self.heading = np.array([0.5])

    svc = LocalService(Rover())
    assert await svc.get("location") == "(1 2)"
    await svc.set("location", "(3 4)")
    assert await svc.get("location") == "(3 4)"
    assert await svc.get("heading") == "(0.5)"
