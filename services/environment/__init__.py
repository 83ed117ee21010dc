"""The environment model: markers and grid layers fused from what other services report.

* :mod:`~services.environment.fusion` — marker association, update and expiry (sans-IO, numpy)
* :mod:`~services.environment.grid` — grid layers (running mean, hit counts) and ``.npy``
* :mod:`~services.environment.heatmap` — a layer as a PNG heat map (Pillow)
* :mod:`~services.environment.observations` — markers as text, in and out
* :mod:`~services.environment.options` — the service's options, checked
* :mod:`~services.environment.sources` — following other services' properties, with backoff
* :mod:`~services.environment.nodes` — the property tree: ``markers.<id>``, ``grid.<layer>``
* :mod:`~services.environment.service` — :class:`EnvironmentModel`, the service (config type
  ``environment``), and :class:`EnvironmentService`, what the class wrapper cannot say alone
"""

from services.environment.fusion import FusedMarker, MarkerFusion, Observation, Update
from services.environment.grid import GridSpec, HitLayer, MeanLayer, to_npy
from services.environment.heatmap import heat_map_png
from services.environment.service import EnvironmentModel, EnvironmentService

__all__ = [
    "EnvironmentModel",
    "EnvironmentService",
    "FusedMarker",
    "GridSpec",
    "HitLayer",
    "MarkerFusion",
    "MeanLayer",
    "Observation",
    "Update",
    "heat_map_png",
    "to_npy",
]
