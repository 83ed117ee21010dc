"""The vision service: a simulated camera that sees robots and objects (see ``docs/vision.md``).

* :mod:`~services.apps.vision.geometry`: poses, the camera frame, field of view and confidence
* :mod:`~services.apps.vision.scene`: the things a camera may see and :func:`look`, what it sees of them
* :mod:`~services.apps.vision.render`: drawing a view and encoding it as JPEG (numpy and Pillow)
* :mod:`~services.apps.vision.camera`: :class:`Camera`, the service, served by :class:`CameraService`
"""

from services.apps.vision.camera import Camera, CameraService

__all__ = ["Camera", "CameraService"]
