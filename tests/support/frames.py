"""A user's service with binary values: a tiny camera of PNG frames, built by hand with zlib.

``FrameSource`` (``type = "tests.support.frames:FrameSource"``, :data:`FRAMES_TYPE`) has a child
``camera`` whose ``frame`` (bytes, ``image/png``, read-only) is a new picture ``rate_hz`` times a
second while the service runs: :func:`frame_png` of the frame's number, a colour ramp that moves
one column per frame (``noisy``: seeded noise, which zlib cannot shrink, for large frames).
``snapshot`` is a writable binary property (``image/png``, at most ``SNAPSHOT_MAX`` bytes) for
Sets; ``weigh`` (an action) takes bytes and answers their count and first byte; ``unplug`` and
``plug`` (actions) detach and attach the camera, so that ``camera.frame`` goes away and comes
back. ``count`` is how many frames were made.
"""

from __future__ import annotations

import asyncio
import struct
import zlib
from typing import Annotated

import numpy as np

from services.kernel.core import Prop, Resource, action

FRAMES_TYPE = "tests.support.frames:FrameSource"
WIDTH = 32
HEIGHT = 24
#: The largest value a Set of ``snapshot`` may carry.
SNAPSHOT_MAX = 64 * 1024


def _chunk(kind: bytes, body: bytes) -> bytes:
    return struct.pack(">I", len(body)) + kind + body + struct.pack(">I", zlib.crc32(kind + body))


def png(pixels: np.ndarray) -> bytes:
    """``pixels`` (height × width × 3, uint8) as an RGB PNG (PNG spec, section 11), filter none."""
    height, width, _ = pixels.shape
    rows = np.zeros((height, width * 3 + 1), dtype=np.uint8)
    rows[:, 1:] = pixels.reshape(height, width * 3)
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)  # 8-bit RGB
    return (
        b"\x89PNG\r\n\x1a\n"
        + _chunk(b"IHDR", header)
        + _chunk(b"IDAT", zlib.compress(rows.tobytes(), 1))
        + _chunk(b"IEND", b"")
    )


def frame_png(number: int, width: int = WIDTH, height: int = HEIGHT, noisy: bool = False) -> bytes:
    """Frame ``number`` of a camera: the same bytes for the same arguments."""
    if noisy:
        pixels = np.random.default_rng(number).integers(0, 256, (height, width, 3), dtype=np.uint8)
        return png(pixels)
    x = (np.arange(width) + number) * 8
    y = np.arange(height) * 10
    pixels = np.zeros((height, width, 3), dtype=np.uint8)
    pixels[:, :, 0] = (x[None, :] & 0xFF).astype(np.uint8)
    pixels[:, :, 1] = (y[:, None] & 0xFF).astype(np.uint8)
    pixels[:, :, 2] = (number * 5) & 0xFF
    return png(pixels)


def solid_png(width: int, height: int, rgb: tuple[int, int, int]) -> bytes:
    """A picture of one colour."""
    return png(np.broadcast_to(np.array(rgb, dtype=np.uint8), (height, width, 3)).copy())


class Camera(Resource):
    """Frames at ``rate_hz`` while the service runs."""

    resource_type = "camera"
    frame: Annotated[bytes, Prop(readonly=True, media_type="image/png", doc="the latest frame")]

    def __init__(self, rate_hz: float, width: int, height: int, noisy: bool) -> None:
        self._rate_hz = rate_hz
        self._size = (width, height, noisy)
        self._count = 0
        self.frame = frame_png(0, *self._size)
        self._task: asyncio.Task[None] | None = None

    async def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="frames")

    async def stop(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.gather(self._task, return_exceptions=True)
            self._task = None

    async def _run(self) -> None:
        while True:
            await asyncio.sleep(1.0 / self._rate_hz)
            self._count += 1
            self.frame = frame_png(self._count, *self._size)


class FrameSource(Resource):
    """A camera of PNG frames, and a writable picture."""

    resource_type = "frame_source"
    snapshot: Annotated[bytes, Prop(media_type="image/png", max_size=SNAPSHOT_MAX, doc="a picture")] = b""

    def __init__(
        self, rate_hz: float = 10.0, width: int = WIDTH, height: int = HEIGHT, noisy: bool = False
    ) -> None:
        self._camera = Camera(rate_hz, width, height, noisy)
        self.attach("camera", self._camera)
        self.snapshot = solid_png(4, 4, (255, 0, 0))

    @property
    def count(self) -> int:
        """Frames made so far."""
        return self._camera._count

    @action
    def weigh(self, data: bytes) -> str:
        """How many bytes were given, and their first one (an action that takes bytes)."""
        return f"({len(data)} {data[0] if data else -1})"

    @action
    def unplug(self) -> str:
        """Take the camera away: ``camera.frame`` is gone."""
        self.detach("camera")
        return "unplugged"

    @action
    def plug(self) -> str:
        """Put the camera back."""
        self.attach("camera", self._camera)
        return "plugged"
