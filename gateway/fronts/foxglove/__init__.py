"""The Foxglove WebSocket protocol on the HTTP front end's port (``/foxglove``, and ``/`` for a
client that offers a Foxglove subprotocol): every property a channel, actions and queries as
services, read-write scalars as parameters. See docs/ros-and-foxglove.md.

:mod:`.protocol` reads and writes the messages, :mod:`.schemas` turns values into typed messages,
:mod:`.catalog` builds what a connection is shown from the models, :mod:`.connection` serves one
client through the engine, and :class:`FoxgloveEndpoint` is what the HTTP front hands an upgrade.
"""

from gateway.fronts.foxglove.endpoint import FoxgloveEndpoint
from gateway.fronts.foxglove.protocol import SUBPROTOCOLS

__all__ = ["SUBPROTOCOLS", "FoxgloveEndpoint"]
