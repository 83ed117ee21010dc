"""The property tree of an environment model: ``markers``, ``markers.<id>``, ``grid``, ``grid.<layer>``.

Each is a child Resource whose own value (``_value``) the class wrapper serves; a marker's node
is attached when the marker is made and detached when it goes, so a Listen hears it come and
go. A layer's own value is bytes, which a namespace cannot hold: its Get and Listen are
answered by :class:`~services.apps.environment.service.EnvironmentService`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Annotated, Any

from services.apps.environment.fusion import MarkerFusion
from services.apps.environment.grid import Layer, to_npy
from services.apps.environment.heatmap import heat_map_png
from services.apps.environment.observations import fused_marker
from services.kernel.backend import Change, Notify, tell_each
from services.kernel.core import Marker, Prop, Resource

__all__ = ["LAYER_META", "NPY", "PNG", "GridLayers", "LayerNode", "MarkerNode", "MarkerTable"]


#: Media types of a layer's value and of its image.
NPY = "application/x-npy"
PNG = "image/png"
#: What ``grid.<layer>.media_type``, ``.gui`` and ``.doc`` answer (the layer's own value is bytes).
LAYER_META = {
    "media_type": NPY,
    "gui": "bytes",
    "doc": "the layer: float32 .npy (numpy.load reads it), row 0 at the origin's y; NaN where a mean"
    " layer has no value, 0 where a hits layer has none",
}


# The docstrings of these classes are the docs Describe gives their properties: plain text.
class MarkerNode(Resource):
    """One fused marker; its value is the marker."""

    def __init__(self, fusion: MarkerFusion, marker_id: str) -> None:
        self._fusion = fusion
        self._id = marker_id

    def _value(self) -> Marker:
        marker = self._fusion.get(self._id)
        return fused_marker(marker) if marker is not None else Marker("marker", {})


class MarkerTable(Resource):
    """The ids of the fused markers; markers.<id> is each one."""

    def __init__(self, fusion: MarkerFusion) -> None:
        self._fusion = fusion

    def _value(self) -> list[str]:
        return self._fusion.ids()


class LayerNode(Resource):
    """``grid.<layer>``: the layer as float32 ``.npy`` (served by
    :class:`~services.apps.environment.service.EnvironmentService`), with ``info`` and ``image`` beside it."""

    def __init__(self, layer: Layer) -> None:
        self._layer = layer
        #: Listeners of the layer's own value (``grid.<layer>``), by token.
        self.listeners: dict[int, Notify] = {}

    @property
    def info(
        self,
    ) -> Annotated[
        list[Any],
        Prop(
            doc="kind, origin (x0 y0), cell (m), shape (rows cols), min, max, filled cells, "
            "values in all, values outside, unit"
        ),
    ]:
        return self._layer.info()

    @property
    def image(self) -> Annotated[bytes, Prop(media_type=PNG, doc="the layer as a heat map, north up")]:
        return self.png()

    def layer_changed(self, path: str) -> None:
        """Tell the listeners of the layer, of ``info`` and of ``image`` that it changed."""
        self.changed("info")
        self.changed("image")
        if self.listeners:
            tell_each(self.listeners, Change(path, self.npy()), what=path)

    def npy(self) -> bytes:
        """The layer's values (float32, NaN where a mean has no value yet) as ``numpy.save`` writes them."""
        return to_npy(self._layer.values())

    def png(self) -> bytes:
        """The layer as a PNG heat map, north up."""
        return heat_map_png(self._layer.values())


class GridLayers(Resource):
    """The names of the grid layers; grid.<layer> is each one."""

    def __init__(self, layers: Mapping[str, Layer]) -> None:
        self._layers = layers

    def _value(self) -> list[str]:
        return list(self._layers)
