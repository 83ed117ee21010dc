"""The browser console's static files: ``gateway/console/`` at ``/`` and ``/console/...``.

Only regular files inside that folder are served: a path with an empty, ``.``, ``..`` or
hidden segment, a backslash or a NUL, a folder (no listings), or a file that resolves
outside the folder (a symbolic link) is NOT_FOUND, however the path was encoded. The
content type comes from this module's table (``.js`` is ``text/javascript``, which browsers
require of ES modules), never from the platform's MIME database; ``Cache-Control:
no-cache`` makes a browser ask again each time, so a new console shows after an upgrade.
"""

from __future__ import annotations

from pathlib import Path
from typing import Final

from aiohttp import hdrs, web

from services.kernel.errors import NotFound

#: The console's folder, shipped as package data of ``gateway``.
CONSOLE_ROOT: Final = Path(__file__).resolve().parents[2] / "console"
INDEX = "index.html"

CONTENT_TYPES: Final[dict[str, str]] = {
    ".html": "text/html; charset=utf-8",
    ".js": "text/javascript; charset=utf-8",
    ".mjs": "text/javascript; charset=utf-8",
    ".css": "text/css; charset=utf-8",
    ".json": "application/json",
    ".map": "application/json",
    ".svg": "image/svg+xml",
    ".png": "image/png",
    ".jpg": "image/jpeg",
    ".jpeg": "image/jpeg",
    ".gif": "image/gif",
    ".webp": "image/webp",
    ".ico": "image/x-icon",
    ".txt": "text/plain; charset=utf-8",
    ".woff2": "font/woff2",
}
_OTHER = "application/octet-stream"


def console_file(root: Path, relative: str) -> Path:
    """The file ``relative`` names under ``root``; NotFound for anything else (see the module docstring)."""
    segments = relative.split("/") if relative else [INDEX]
    for segment in segments:
        if not segment or segment.startswith(".") or "\\" in segment or "\0" in segment:
            raise NotFound(f"no console file {relative[:200]!r}")
    real_root = root.resolve()
    try:
        path = real_root.joinpath(*segments).resolve()
    except (OSError, RuntimeError, ValueError):
        raise NotFound(f"no console file {relative[:200]!r}") from None
    if not path.is_relative_to(real_root) or not path.is_file():
        raise NotFound(f"no console file {relative[:200]!r}")
    return path


class Console:
    """Serves the files of one console folder."""

    def __init__(self, root: Path = CONSOLE_ROOT) -> None:
        self.root = root

    async def file(self, request: web.Request) -> web.FileResponse:
        path = console_file(self.root, request.match_info.get("file", ""))
        return web.FileResponse(
            path,
            headers={
                hdrs.CONTENT_TYPE: CONTENT_TYPES.get(path.suffix.lower(), _OTHER),
                hdrs.CACHE_CONTROL: "no-cache",
                "X-Content-Type-Options": "nosniff",
            },
        )
