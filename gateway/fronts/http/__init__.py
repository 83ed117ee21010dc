"""The HTTP/JSON + Server-Sent-Events front end of the gateway, and the console's static files.

* :mod:`~gateway.fronts.http.front` — :class:`HttpFront`: the aiohttp application, start and stop.
* :mod:`~gateway.fronts.http.api` — the JSON routes: services, model, Get, Set, health.
* :mod:`~gateway.fronts.http.events` — Listen as Server-Sent Events.
* :mod:`~gateway.fronts.http.image_stream` — a binary property live, as ``multipart/x-mixed-replace``.
* :mod:`~gateway.fronts.http.places` — the bound on open event and image streams.
* :mod:`~gateway.fronts.http.binary` — binary values: base64 in JSON, raw answers, media types.
* :mod:`~gateway.fronts.http.console` — the browser console's files.
* :mod:`~gateway.fronts.http.bodies` — request bodies and parameters, checked.
* :mod:`~gateway.fronts.http.safety` — Origin, Host and Content-Type checks; identity.
* :mod:`~gateway.fronts.http.errors` — errors as JSON with the HTTP status of their code.
* :mod:`~gateway.fronts.http.openapi` — the OpenAPI 3.1 document.

The routes and formats are documented in ``docs/http-api.md``.
"""

from gateway.fronts.http.front import HttpFront, WebSocketRoute

__all__ = ["HttpFront", "WebSocketRoute"]
