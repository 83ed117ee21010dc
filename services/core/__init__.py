"""The Property Service core: write a service as a plain Python class, serve it as a Backend.

* :class:`Resource` — base class of every service object (attributes, ``@property``,
  ``@functional`` methods and child namespaces become properties).
* :class:`Prop` — metadata in ``Annotated[T, Prop(...)]``; :func:`functional` — marks
  functional properties.
* :class:`LocalService` — serves a Resource in-process as a ``services.backend.Backend``.
* :func:`start_tree` / :func:`stop_tree` — run a Resource's lifecycle hooks and its children's.
* ``RESERVED_NAMES`` — names no member or child may take (``properties``, ``parameters``, ``gui``, ``doc``).
* ``Vector`` and ``Marker`` — the value types a property's annotation may name besides the builtins
  (from :mod:`services.values`).
"""

from services.core.local import LocalService
from services.core.metadata import RESERVED_NAMES, Prop, functional
from services.core.resource import Resource, start_tree, stop_tree
from services.values import Marker, Vector

__all__ = [
    "RESERVED_NAMES",
    "LocalService",
    "Marker",
    "Prop",
    "Resource",
    "Vector",
    "functional",
    "start_tree",
    "stop_tree",
]
