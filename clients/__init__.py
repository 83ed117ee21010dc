"""Python client SDK (sync and asyncio) and the ``psctl`` command line.

``AsyncClient`` and ``Client`` call a Property Service gateway; ``Session``
multiplexes many calls over one stream; ``clients.values`` decodes value
texts; ``ClientCredentials`` carry TLS files and a bearer token; every
failure is a ``PropertyServiceError`` subclass.

The public surface of each module (its ``__all__``) is re-exported here.
"""

from typing import Any

from clients import aio, credentials, errors, sync, values
from clients.aio import *  # noqa: F403
from clients.credentials import *  # noqa: F403
from clients.errors import *  # noqa: F403
from clients.sync import *  # noqa: F403
from clients.values import *  # noqa: F403

__all__ = aio.__all__ + credentials.__all__ + errors.__all__ + sync.__all__ + values.__all__


def __getattr__(name: str) -> Any:
    # clients.Vector is numpy's array type, named on first use so that importing the SDK does not
    # load numpy (see clients.values).
    if name == "Vector":
        return values.Vector
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
