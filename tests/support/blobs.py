"""A service with binary properties, for the tests of binary values (served by a real gateway).

Named in a config by import path (``support.blobs:Blobs``, with ``tests/`` on ``PYTHONPATH``):

* ``picture``: read-write bytes, ``image/png``, at most 8 MiB a Set (more than one message);
* ``small``: read-write bytes of at most 16;
* ``note``: text, as every property before binary values;
* ``frame``: read-only bytes, ``image/jpeg``, renewed ``rate_hz`` times a second with
  ``frame_bytes`` bytes once ``stream`` is set to true (a fast, large, changing binary value);
* ``checksum`` (query): the length and CRC-32 of ``picture``;
* ``big`` (query): ``size`` zero bytes (an answer bigger than a message can carry);
* ``echo`` (action): answers the bytes it is given, reversed.

:func:`start_blobs` starts a real gateway process serving it as ``blobs``.
"""

from __future__ import annotations

import asyncio
import contextlib
import os
import sys
import zlib
from pathlib import Path
from typing import TYPE_CHECKING, Annotated

from services.kernel.core import Prop, Resource, action, query

if TYPE_CHECKING:
    from support.gateway_process import GatewayProcess

#: The config serving :class:`Blobs` as ``blobs``.
BLOBS_CONFIG = '[[services]]\nname = "blobs"\ntype = "support.blobs:Blobs"\n'


def start_blobs(tmp: Path, config: str = BLOBS_CONFIG, *extra_args: str) -> GatewayProcess:
    """A ready gateway process serving ``config`` (by default :class:`Blobs` as ``blobs``), with
    ``tests/`` on its import path; the caller stops it."""
    # Imported here: the gateway process imports this module for the class alone.
    from support.gateway_process import ROOT, GatewayProcess

    path = tmp / f"blobs-{len(list(tmp.glob('blobs-*.toml')))}.toml"
    path.write_text(config)
    args = [sys.executable, "-m", "gateway.cli", "serve", "--config", str(path), "--listen", "127.0.0.1:0"]
    env = {"PYTHONPATH": os.pathsep.join([str(ROOT / "tests"), str(ROOT)])}
    gw = GatewayProcess([*args, *extra_args], env=env)
    try:
        gw.wait_ready()
    except BaseException:
        gw.stop()
        raise
    return gw


class Blobs(Resource):
    """Binary values of several kinds, and one text value."""

    resource_type = "blobs"
    picture: Annotated[bytes, Prop(media_type="image/png", max_size=8 * 1024 * 1024, doc="a picture")] = b""
    small: Annotated[bytes, Prop(max_size=16)] = b""
    note: str = ""
    frame: Annotated[bytes, Prop(readonly=True, media_type="image/jpeg")] = b""
    frame_bytes: int = 200_000
    rate_hz: float = 50.0
    stream: bool = False

    def __init__(self) -> None:
        super().__init__()
        self._task: asyncio.Task[None] | None = None
        self._count = 0

    async def start(self) -> None:
        self._task = asyncio.create_task(self._run())

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(1 / max(self.rate_hz, 0.1))
            if self.stream:
                self._count += 1
                # Each frame differs from the last (a counter at the head), and is the size asked.
                head = self._count.to_bytes(8, "big")
                self.frame = head + bytes([self._count % 256]) * max(self.frame_bytes - 8, 0)

    @query
    def checksum(self) -> str:
        """The length and CRC-32 of ``picture``."""
        return f"({len(self.picture)} {zlib.crc32(self.picture)})"

    @query
    def big(self, size: int = 0) -> bytes:
        """``size`` zero bytes."""
        return bytes(size)

    @action
    def echo(self, data: Annotated[bytes, Prop(media_type="application/octet-stream")]) -> bytes:
        """Answer the bytes given, reversed."""
        return data[::-1]
