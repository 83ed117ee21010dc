"""The environment model: markers and grid layers fused from what other services report.

* :mod:`~services.apps.environment.fusion` — marker association, update and expiry (sans-IO, numpy)
* :mod:`~services.apps.environment.grid` — grid layers (running mean, hit counts) and ``.npy``
* :mod:`~services.apps.environment.heatmap` — a layer as a PNG heat map (Pillow)
* :mod:`~services.apps.environment.observations` — markers as text, in and out
* :mod:`~services.apps.environment.options` — the service's options, checked
* :mod:`~services.apps.environment.sources` — following other services' properties, with backoff
* :mod:`~services.apps.environment.nodes` — the property tree: ``markers.<id>``, ``grid.<layer>``
* :mod:`~services.apps.environment.service` — :class:`EnvironmentModel`, the service (config type
  ``environment``), and :class:`EnvironmentService`, what the class wrapper cannot say alone
"""

from services.apps.environment.fusion import FusedMarker, MarkerFusion, Observation, Update
from services.apps.environment.grid import GridSpec, HitLayer, MeanLayer, to_npy
from services.apps.environment.heatmap import heat_map_png
from services.apps.environment.service import EnvironmentModel, EnvironmentService

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
