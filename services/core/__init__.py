"""The Property Service core: write a service as a plain Python class, serve it as a Backend.

* :class:`Resource` — base class of every service object (attributes, ``@property``,
  ``@functional`` methods and child namespaces become properties).
* :class:`Prop` — metadata in ``Annotated[T, Prop(...)]``; :func:`functional` — marks
  functional properties.
* :class:`LocalService` — serves a Resource in-process as a ``services.backend.Backend``.
"""

from services.core.local import LocalService
from services.core.metadata import Prop, functional
from services.core.resource import Resource

__all__ = ["LocalService", "Prop", "Resource", "functional"]
