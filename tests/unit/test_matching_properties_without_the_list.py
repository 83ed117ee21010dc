"""A service answers which of its properties match a wildcard, and says where its list changed,
without ever formatting its ``properties`` list: ``Backend.match_properties`` and
``Backend.listen_properties``, in-process (the class wrapper's walk) and by default (a backend
that only has its ``properties`` list and model)."""

from __future__ import annotations

from collections.abc import AsyncIterator

import pytest
from support.fake_backend import DictBackend
from support.group_support import MemoryDirectory
from support.waiting import wait_until

from gateway.engine.listen.matched import MatchedPaths
from services.apps.registry import Registry, RegistryService
from services.kernel.backend import Change
from services.kernel.core import LocalService, Resource
from services.kernel.errors import Code, PropertyError
from services.kernel.model import Access
from services.kernel.paths import compile_pattern, is_below
from services.kernel.values import MAX_VALUE_LENGTH

SERVICES = 40


@pytest.fixture
async def registry() -> AsyncIterator[LocalService]:
    """A registry following a directory of ``SERVICES`` services (dev00 … dev39)."""
    directory = MemoryDirectory()
    reg = Registry(directory=directory, period=0)
    service = RegistryService(reg)
    await service.start()
    await reg.start()
    for i in range(SERVICES):
        await directory.add(f"dev{i:02d}", DictBackend({"a": "1"}))
    yield service
    await reg.stop()
    await service.aclose()


async def listed(service: LocalService, pattern: str, under: str = "") -> list[str]:
    """What filtering the ``properties`` list gives: what ``match_properties`` must answer."""
    matches = compile_pattern(pattern)
    return [n for n in await service.properties() if matches(n) and (not under or is_below(n, under))]


@pytest.mark.parametrize(
    "pattern",
    [
        "services.*.state",
        "services.*",
        "*",
        "services.dev07.*",
        "services.*.*",
        "services.dev07.state",
        "x.*",
    ],
)
async def test_a_registry_matches_as_its_properties_list_would(registry: LocalService, pattern: str) -> None:
    found = [p.name for p in await registry.match_properties(pattern)]
    assert found == await listed(registry, pattern)
    if pattern in ("services.*.state", "services.*"):
        assert len(found) == SERVICES  # one for each service


async def test_below_a_name_only_what_lies_there_matches(registry: LocalService) -> None:
    assert [p.name for p in await registry.match_properties("services.*.state", "services.dev07")] == [
        "services.dev07.state"
    ]
    assert [p.name for p in await registry.match_properties("services.*", "services.dev07")] == [
        "services.dev07"
    ]
    found = [p.name for p in await registry.match_properties("services.*.*", "services.dev07")]
    assert found == await listed(registry, "services.*.*", "services.dev07") and "services.dev07.url" in found
    # A name deeper than the pattern, a name that is not there, one the pattern does not allow.
    assert await registry.match_properties("services.*", "services.dev07.state") == []
    assert await registry.match_properties("services.*.state", "services.nobody") == []
    assert await registry.match_properties("licences.*", "services.dev07") == []


async def test_the_models_say_what_a_listen_may_follow(registry: LocalService) -> None:
    models = {p.name: p for p in await registry.match_properties("*")}
    assert models["services"].type == "namespace"
    assert models["find"].access is Access.QUERY  # a wildcard Listen skips it
    state = (await registry.match_properties("services.*.state", "services.dev03"))[0]
    assert state.access is Access.READ and state.type == "text"


class Members(Resource):
    """Holds Backend children, as a group holds its member devices."""


async def test_backend_children_answer_the_rest_of_the_pattern() -> None:
    root = Members()
    root.attach("m1", DictBackend({"a": "1", "b": "2"}))
    root.attach("m2", DictBackend({"a": "3"}))
    root.attach("away", DictBackend({"a": "4"}, unreachable=True))
    service = LocalService(root)
    assert [p.name for p in await service.match_properties("*.a")] == ["m1.a", "m2.a"]
    assert [p.name for p in await service.match_properties("*.*", "m1")] == ["m1.a", "m1.b"]
    assert [p.name for p in await service.match_properties("*")] == ["m1", "m2", "away"]
    # As the list leaves out the member that cannot be reached, so do the matches.
    assert [p.name for p in await service.match_properties("*.*")] == await listed(service, "*.*")


async def test_the_default_filters_the_list_and_the_model() -> None:
    device = DictBackend({"a": "1", "b.x": "2", "b.y": "3"})
    assert [p.name for p in await device.match_properties("b.*")] == ["b.x", "b.y"]
    assert [p.name for p in await device.match_properties("*.*", "b")] == ["b.x", "b.y"]
    assert await device.match_properties("*", "b") == []
    assert (await device.match_properties("a"))[0].access is Access.UNKNOWN


async def test_the_default_says_so_when_the_list_is_longer_than_a_value() -> None:
    device = DictBackend({f"property{i:05d}": "1" for i in range(MAX_VALUE_LENGTH // 10)})
    with pytest.raises(PropertyError) as err:
        await device.match_properties("*")
    assert err.value.code is Code.INVALID_ARGUMENT and str(MAX_VALUE_LENGTH) in err.value.message


class Kids(Resource):
    """A namespace whose children come and go."""


class Tree(Resource):
    kids: Kids

    def __init__(self) -> None:
        self.kids = Kids()


async def test_a_local_service_says_where_its_tree_changed() -> None:
    tree = Tree()
    service = LocalService(tree)
    heard: list[Change] = []
    sub = await service.listen_properties(heard.append)
    tree.kids.attach("x", Kids())
    tree.kids.detach("x")
    assert [(c.path, c.value) for c in heard] == [("kids.x", ""), ("kids.x", "")]
    await sub.close()
    tree.kids.attach("y", Kids())
    assert len(heard) == 2
    await service.aclose()


async def test_a_backend_child_s_list_change_is_told_under_its_name() -> None:
    root = Members()
    member = DictBackend({"a": "1"})
    root.attach("m1", member)
    inner = Tree()
    root.attach("nested", LocalService(inner))
    service = LocalService(root)
    heard: list[str] = []
    sub = await service.listen_properties(lambda change: heard.append(change.path))
    member.add("b", "2")  # a device that only has its list: "somewhere in m1"
    inner.kids.attach("z", Kids())  # an in-process child says where
    await wait_until(lambda: heard == ["m1", "nested.kids.z"], what="both changes, each under its child")
    await sub.close()
    await wait_until(lambda: member.listeners("properties") == 0, what="the child's list no longer followed")
    await service.aclose()


def test_matched_paths_tell_what_lies_below_a_name() -> None:
    paths = MatchedPaths(["a.b", "a-b.c", "ab.c", "a.b.c", "a"])
    assert paths.below("a") == {"a", "a.b", "a.b.c"}
    assert paths.below("a.b") == {"a.b", "a.b.c"}
    assert paths.below("a-b") == {"a-b.c"}
    assert paths.below("") == {"a", "a.b", "a-b.c", "ab.c", "a.b.c"}
    paths.discard("a.b")
    paths.add("a.c")
    paths.add("a.c")
    assert paths.below("a") == {"a", "a.b.c", "a.c"} and len(paths) == 5 and "a.c" in paths
    assert list(paths) == sorted(paths.below(""))
    many = [f"b.{i:03d}" for i in range(100)]
    paths.update(many)
    paths.update(["a.d"])
    assert paths.below("b") == set(many) and list(paths) == sorted(paths.below("")) and "a.d" in paths
