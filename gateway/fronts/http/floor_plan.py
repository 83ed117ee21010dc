"""The console's floor plan (``[console] map_image`` and ``map_extent``): drawn under the map's robots.

``GET /console/floor-plan.json`` says whether there is one and where it lies,
``{"image": "/console/floor-plan", "extent": [x0, y0, x1, y1]}`` (``"image": null`` when the
config names none); ``GET /console/floor-plan`` is the picture. Like the console's own files it
is served to whoever may load the page, with no identity asked: put nothing in it that the page
itself may not show. The config names an existing file (checked when the gateway starts); one
removed later is NOT_FOUND, logged once as a warning.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Final

from aiohttp import hdrs, web

from gateway.config import MAP_IMAGE_TYPES, ConsoleSection
from services.kernel.errors import NotFound

log = logging.getLogger("gateway.fronts.http")

#: The routes, beside the console's files (registered before ``/console/{file}``).
DESCRIPTION_ROUTE: Final = "/console/floor-plan.json"
IMAGE_ROUTE: Final = "/console/floor-plan"


class FloorPlan:
    """Serves the floor plan a ``[console]`` section names, and says where it lies."""

    def __init__(self, section: ConsoleSection) -> None:
        self.path = Path(section.map_image) if section.map_image else None
        self.extent = list(section.map_extent)
        self._missing_logged = False

    async def description(self, request: web.Request) -> web.Response:
        image = IMAGE_ROUTE if self.path is not None else None
        return web.json_response(
            {"image": image, "extent": self.extent if image else None},
            headers={hdrs.CACHE_CONTROL: "no-cache"},
        )

    async def image(self, request: web.Request) -> web.FileResponse:
        path = self.path
        if path is None:
            raise NotFound("no floor plan: the config's [console] map_image names none")
        if not path.is_file():
            if not self._missing_logged:
                self._missing_logged = True
                log.warning(
                    "the floor plan %s ([console] map_image) is gone: the map is drawn without it", path
                )
            raise NotFound("the floor plan's file is gone (see the gateway's log)")
        self._missing_logged = False
        return web.FileResponse(
            path,
            headers={
                hdrs.CONTENT_TYPE: MAP_IMAGE_TYPES[path.suffix.lower()],
                hdrs.CACHE_CONTROL: "no-cache",
                "X-Content-Type-Options": "nosniff",
                # An SVG opened on its own runs no script and loads nothing.
                "Content-Security-Policy": "default-src 'none'; style-src 'unsafe-inline'; sandbox",
            },
        )
