"""The Property Service core: write a service as a plain Python class, serve it as a Backend.

* :class:`Resource` — base class of every service object (attributes, ``@property``,
  ``@action``/``@query`` methods and child namespaces become properties).
* :class:`Prop` — metadata in ``Annotated[T, Prop(...)]`` (unit, range, choices, length, ...).
* :func:`action` — a method a Set invokes; :func:`query` — a method a Get calls, declared
  never to change state; :func:`read_write` — a method a Get calls without a value and a Set
  with one (a value computed by asking others, set by telling them); :func:`functional` — the
  former name of :func:`action`.
* :class:`LocalService` — serves a Resource in-process as a ``services.kernel.backend.Backend``;
  :func:`serve` — the backend a Resource's class asks for (``Resource.served_by``, by default LocalService).
* :func:`start_tree` / :func:`stop_tree` — run a Resource's lifecycle hooks and its children's.
* ``RESERVED_NAMES`` — names no member or child may take (``properties``, ``parameters``, ``gui``, ``doc``).
* ``Vector`` and ``Marker`` — the value types a property's annotation may name besides the builtins
  (from :mod:`services.kernel.values`).
"""

from services.kernel.core.local import LocalService, serve
from services.kernel.core.metadata import RESERVED_NAMES, Prop, action, functional, query, read_write
from services.kernel.core.resource import Resource, start_tree, stop_tree
from services.kernel.values import Marker, Vector

__all__ = [
    "RESERVED_NAMES",
    "LocalService",
    "Marker",
    "Prop",
    "Resource",
    "Vector",
    "action",
    "functional",
    "query",
    "read_write",
    "serve",
    "start_tree",
    "stop_tree",
]
