"""The rosbridge v2 front end: roslibjs, roslibpy and ROS web tools over a WebSocket.

* :mod:`~gateway.fronts.rosbridge.protocol` — the protocol's messages read and written, no I/O;
* :mod:`services.kernel.ros_names` — topic and service names ↔ services' properties (in the kernel:
  the ROS 2 export of a recording names its topics the same way);
* :mod:`services.kernel.ros_messages` — ROS message types of the property model, values in and out
  (in the kernel, shared with the ROS 2 export);
* :mod:`~gateway.fronts.rosbridge.rosapi` — rosapi's introspection from the registry and the models;
* :mod:`~gateway.fronts.rosbridge.connection` — one client's operations through the engine;
* :mod:`~gateway.fronts.rosbridge.websocket` — the endpoint the HTTP front end serves at ``/rosbridge``.

docs/ros-and-foxglove.md says what a client sees.
"""

from gateway.fronts.rosbridge.websocket import ROSBRIDGE_PATH, RosbridgeEndpoint

__all__ = ["ROSBRIDGE_PATH", "RosbridgeEndpoint"]
