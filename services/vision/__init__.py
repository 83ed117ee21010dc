"""The vision service: a simulated camera that sees robots and objects (see ``docs/vision.md``).

* :mod:`~services.vision.geometry`: poses, the camera frame, field of view and confidence
* :mod:`~services.vision.scene`: the things a camera may see and :func:`look`, what it sees of them
* :mod:`~services.vision.render`: drawing a view and encoding it as JPEG (numpy and Pillow)
* :mod:`~services.vision.camera`: :class:`Camera`, the service, served by :class:`CameraService`
"""

from services.vision.camera import Camera, CameraService

__all__ = ["Camera", "CameraService"]
