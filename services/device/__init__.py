"""The device side of the line protocol: serve any Backend to line-protocol clients.

* :class:`DeviceServer` — one backend on TCP (``serve_tcp``, or ``dial`` out to
  a gateway's line listener), a serial port (``serve_serial``) or a pty of its
  own (``serve_pty``); module ``server``.
* :class:`DeviceSession` — one connection's protocol session; module ``session``
  (its outbox of replies and conflated events: ``outbox``).
* ``transports`` — serial ports, ptys and pipes as asyncio streams.
* ``cli`` — the device command, ``python -m services.device`` and
  ``psgateway device``.
"""

from services.device.server import DeviceServer
from services.device.session import CALL_TIMEOUT, MAX_IN_FLIGHT, MAX_SUBSCRIPTIONS, DeviceSession

__all__ = ["CALL_TIMEOUT", "MAX_IN_FLIGHT", "MAX_SUBSCRIPTIONS", "DeviceServer", "DeviceSession"]
