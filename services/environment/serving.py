"""Serving an environment model: the class wrapper, and the calls it cannot express alone."""

from __future__ import annotations

import itertools
from collections.abc import Mapping
from dataclasses import replace
from typing import TYPE_CHECKING

from services.backend import NO_PARAMS, Notify, Subscription
from services.core import LocalService, Resource
from services.environment.nodes import LAYER_META, NPY, LayerNode
from services.errors import InvalidArgument
from services.model import PropertyModel, ServiceModel
from services.values import Value

if TYPE_CHECKING:
    from services.environment.service import EnvironmentModel

__all__ = ["EnvironmentService"]


class _LayerSubscription(Subscription):
    __slots__ = ("_node", "_token")

    def __init__(self, node: LayerNode, token: int) -> None:
        self._node = node
        self._token = token

    async def close(self) -> None:
        self._node.listeners.pop(self._token, None)


class EnvironmentService(LocalService):
    """Serves an :class:`EnvironmentModel`: the class wrapper, and what it cannot say alone.

    * ``grid.<layer>`` is a namespace (``info``, ``image`` under it) whose own value is binary,
      the layer as ``.npy``: this class answers its Get, Listen, ``media_type`` and model.
    * ``class`` is a word Python keeps for itself, so ``find``'s keyword is ``kind``; a Get of
      ``find`` with ``class=...`` is taken as ``kind=...``.
    """

    obj: EnvironmentModel

    def __init__(self, obj: Resource, url: str = "local") -> None:
        super().__init__(obj, url)
        self._layer_tokens = itertools.count()

    def _layer(self, path: str) -> LayerNode | None:
        head, _, name = path.partition(".")
        return self.obj.layer_nodes.get(name) if head == "grid" else None

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> Value:
        node = self._layer(path)
        if node is not None:
            if params:
                raise InvalidArgument(f"`{path}` takes no parameters")
            return node.npy()
        head, _, meta = path.rpartition(".")
        if meta in LAYER_META and self._layer(head) is not None:
            if params:
                raise InvalidArgument(f"`{path}` takes no parameters")
            return LAYER_META[meta]
        if path == "find" and "class" in params:
            if "kind" in params:
                raise InvalidArgument("`find`: give class or kind, not both")
            params = {("kind" if k == "class" else k): v for k, v in params.items()}
        return await super().get(path, params)

    async def listen(self, path: str, notify: Notify, params: Mapping[str, str] = NO_PARAMS) -> Subscription:
        node = self._layer(path)
        if node is None:
            return await super().listen(path, notify, params)
        token = next(self._layer_tokens)
        node.listeners[token] = notify
        return _LayerSubscription(node, token)

    async def describe(self) -> ServiceModel:
        model = await super().describe()
        doc = LAYER_META["doc"]
        layers = {f"grid.{name}" for name in self.obj.layer_nodes}

        def typed(p: PropertyModel) -> PropertyModel:
            # Nodes with a value of their own, which the class wrapper calls namespaces: typed,
            # they are values a wildcard Get (`markers.*`) reads and a client knows how to parse.
            if p.name in layers:
                return replace(p, type="bytes", media_type=NPY, doc=doc, gui="bytes")
            if p.name in ("markers", "grid"):
                return replace(p, type="names", gui="list")
            if p.name.startswith("markers.") and p.type == "namespace":
                return replace(p, type="marker", gui="marker")
            return p

        return replace(model, properties=tuple(typed(p) for p in model.properties))
