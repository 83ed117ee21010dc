"""Drawing what a camera sees and encoding it as JPEG.

A pinhole view, level with the ground: the sky above the horizon (the middle
row), the floor below it with a line at every few metres, and each thing in
view as a filled shape standing on the floor, its width and height scaled
with distance (farthest first, so nearer things cover farther ones), its id
above it. The top-left corner shows the frame number and the time, so
consecutive frames always differ.

The background depends only on the resolution, the field of view, the
camera's height and its range: it is drawn once per change of those and
copied for each frame. The shapes are numpy slices; Pillow draws the text
and encodes the JPEG (both release the GIL while they work).
"""

from __future__ import annotations

import io
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw, ImageFont

from services.apps.vision.scene import Sighting

__all__ = ["Renderer", "View"]

#: Labels drawn at most in one frame (the nearest): a crowd of thousands stays cheap and legible.
MAX_LABELS = 64
#: Closest a thing may be drawn, m in front of the lens: nearer, its size would divide by ~0.
_NEAREST = 0.05
_SKY_TOP = np.array([70, 120, 200], dtype=np.float32)
_SKY_HORIZON = np.array([190, 210, 235], dtype=np.float32)
_FLOOR_FAR = np.array([120, 115, 105], dtype=np.float32)
_FLOOR_NEAR = np.array([70, 65, 60], dtype=np.float32)
_FLOOR_LINE = np.array([150, 145, 135], dtype=np.uint8)
#: Distances (m) at which the floor carries a line, as far as the range reaches.
_FLOOR_LINES = (0.5, 1.0, 2.0, 3.0, 5.0, 7.5, 10.0, 15.0, 20.0, 30.0, 50.0, 100.0)


@dataclass(frozen=True, slots=True)
class View:
    """Everything one frame shows: a snapshot taken on the event loop, drawn on another thread."""

    sightings: Sequence[Sighting]
    number: int
    #: Seconds since the epoch, for the time shown.
    stamp: float
    quality: int


class Renderer:
    """Draws views of one camera geometry (resolution, field of view, eye height, range)."""

    def __init__(self, width: int, height: int, fov_rad: float, eye_height: float, range_m: float) -> None:
        self.width = width
        self.height = height
        self.fov = fov_rad
        self.eye = eye_height
        self.range = range_m
        #: Pixels per unit of (lateral offset / forward distance): the pinhole's focal length.
        self.focal = (width / 2) / math.tan(fov_rad / 2)
        self.horizon = height // 2
        self.background = self._background()
        self._font = ImageFont.load_default()

    def _background(self) -> npt.NDArray[np.uint8]:
        w, h, horizon = self.width, self.height, self.horizon
        image = np.empty((h, w, 3), dtype=np.uint8)
        sky = np.linspace(0.0, 1.0, max(horizon, 1), dtype=np.float32)[:, None]
        image[:horizon] = ((1 - sky) * _SKY_TOP + sky * _SKY_HORIZON).astype(np.uint8)[:horizon, None, :]
        floor = np.linspace(0.0, 1.0, max(h - horizon, 1), dtype=np.float32)[:, None]
        image[horizon:] = ((1 - floor) * _FLOOR_FAR + floor * _FLOOR_NEAR).astype(np.uint8)[
            : h - horizon, None, :
        ]
        if self.eye > 0:
            for d in _FLOOR_LINES:
                if d > self.range:
                    break
                row = horizon + round(self.focal * self.eye / d)
                if horizon < row < h:
                    image[row] = _FLOOR_LINE
        return image

    def draw(self, view: View) -> npt.NDArray[np.uint8]:
        """The frame as an H x W x 3 array of RGB, without the text."""
        image = self.background.copy()
        for s in sorted(view.sightings, key=lambda s: -s.distance):
            self._shape(image, s)
        return image

    def _box(self, s: Sighting) -> tuple[float, float, float, float] | None:
        forward, left, below = float(s.camera[0]), float(s.camera[1]), float(s.camera[2])
        if forward < _NEAREST:
            return None
        scale = self.focal / forward
        u = self.width / 2 - left * scale
        half = s.thing.size * scale / 2
        bottom = self.horizon - below * scale
        top = self.horizon - (below + s.thing.size) * scale
        return u - half, top, u + half, bottom

    def _shape(self, image: npt.NDArray[np.uint8], s: Sighting) -> None:
        box = self._box(s)
        if box is None:
            return
        x0, y0 = max(0, int(box[0])), max(0, int(box[1]))
        x1, y1 = min(self.width, math.ceil(box[2])), min(self.height, math.ceil(box[3]))
        if x0 >= x1 or y0 >= y1:
            return
        fade = 1.0 - 0.35 * min(1.0, s.distance / self.range)  # farther things are dimmer
        fill = (np.asarray(s.thing.colour) * 255 * fade).astype(np.uint8)
        edge = (fill * 0.55).astype(np.uint8)
        patch = image[y0:y1, x0:x1]
        if "ball" in s.thing.cls:
            cx, cy = (box[0] + box[2]) / 2, (box[1] + box[3]) / 2
            rx, ry = max((box[2] - box[0]) / 2, 0.5), max((box[3] - box[1]) / 2, 0.5)
            ys = ((np.arange(y0, y1) + 0.5 - cy) / ry)[:, None]
            xs = ((np.arange(x0, x1) + 0.5 - cx) / rx)[None, :]
            r2 = xs * xs + ys * ys
            patch[r2 <= 1.0] = edge
            patch[r2 <= 0.8] = fill
            return
        patch[:] = edge
        border = 2 if min(x1 - x0, y1 - y0) > 6 else 0
        patch[border : patch.shape[0] - border, border : patch.shape[1] - border] = fill

    def encode(self, view: View) -> bytes:
        """The frame as JPEG at the view's quality, with the labels and the frame's number and time."""
        image = Image.fromarray(self.draw(view), "RGB")
        pen = ImageDraw.Draw(image)
        for s, box in self._labelled(view.sightings):
            wide = pen.textlength(s.thing.id, font=self._font)
            x = min(max(0.0, (box[0] + box[2]) / 2 - wide / 2), self.width - wide)
            y = min(max(0.0, box[1] - 13), self.height - 12.0)
            pen.text((x, y), s.thing.id, fill=(255, 255, 255), font=self._font)
        clock = time.strftime("%H:%M:%S", time.gmtime(view.stamp)) + f".{int(view.stamp * 1000) % 1000:03d}"
        header = f"#{view.number}  {clock} UTC  {len(view.sightings)} in view"
        pen.rectangle((0, 0, 8 + pen.textlength(header, font=self._font), 15), fill=(0, 0, 0))
        pen.text((4, 2), header, fill=(255, 255, 255), font=self._font)
        out = io.BytesIO()
        image.save(out, "JPEG", quality=view.quality)
        return out.getvalue()

    def _labelled(
        self, sightings: Sequence[Sighting]
    ) -> list[tuple[Sighting, tuple[float, float, float, float]]]:
        """The things whose label is drawn, nearest first: at most MAX_LABELS, and none whose
        top is hidden behind a nearer thing (a label over another thing's face would lie)."""
        shown: list[tuple[Sighting, tuple[float, float, float, float]]] = []
        boxes: list[tuple[float, float, float, float]] = []
        for s in sorted(sightings, key=lambda s: s.distance)[: 4 * MAX_LABELS]:  # bounded: N^2 below
            box = self._box(s)
            if box is None or box[2] < 0 or box[0] > self.width:
                continue
            top = ((box[0] + box[2]) / 2, box[1] + 1)
            hidden = any(b[0] <= top[0] <= b[2] and b[1] <= top[1] <= b[3] for b in boxes)
            boxes.append(box)
            if not hidden:
                shown.append((s, box))
                if len(shown) >= MAX_LABELS:
                    break
        return shown
