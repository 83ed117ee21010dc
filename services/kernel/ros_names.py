"""ROS names for the gateway's properties: a topic or service is ``/SERVICE/PATH`` with the
path's dots as slashes (``/scout1/sensors/battery`` is ``scout1`` ``sensors.battery``).

Beside the property names stand the conventions ROS tools expect of a mobile robot: a
``geometry_msgs/Twist`` on ``/ROBOT/cmd_vel`` drives its ``velocity``, and ``/ROBOT/odom``
(``nav_msgs/Odometry``) and ``/ROBOT/pose`` (``geometry_msgs/Pose2D``) give its ``location``.
Nothing here does I/O.
"""

from __future__ import annotations

from dataclasses import dataclass

from services.kernel.errors import InvalidArgument

#: Robot conventions: the last name of the topic → (the property it stands for, its one message type).
CONVENTIONS: dict[str, tuple[str, str]] = {
    "cmd_vel": ("velocity", "geometry_msgs/Twist"),
    "odom": ("location", "nav_msgs/Odometry"),
    "pose": ("location", "geometry_msgs/Pose2D"),
}
#: The resource type whose services get the conventions (what the registry calls a mobile robot).
MOBILE_ROBOT = "mobile_robot"
#: Longest ROS name accepted: a name is echoed in errors and kept per subscription.
MAX_NAME_CHARS = 1024


@dataclass(frozen=True, slots=True)
class Target:
    """Where a ROS name points: a service's property, and the convention it was reached by, if any."""

    service: str
    path: str
    #: ``cmd_vel``, ``odom`` or ``pose`` when the name is a robot convention; "" for a property's own name.
    convention: str = ""


def ros_name(service: str, path: str) -> str:
    """``/SERVICE/PATH`` with the path's dots as slashes."""
    return f"/{service}/{path.replace('.', '/')}"


def global_name(name: str) -> str:
    """A relative name (``rosapi/topics``, as roslibjs names rosapi's services) made global, as
    rosbridge resolves it: the gateway has no namespaces, so ``/`` goes before it."""
    return name if name.startswith("/") else "/" + name


def parse_name(name: object, what: str = "topic") -> Target:
    """A topic or service name as the property it names; InvalidArgument for anything else.

    ``/scout1/cmd_vel`` names ``scout1`` ``velocity`` by convention; whether ``scout1`` is a
    robot is the caller's to check (:func:`convention_applies`).
    """
    if not isinstance(name, str) or not name:
        raise InvalidArgument(f"a {what} name must be a non-empty string like /scout1/location")
    if len(name) > MAX_NAME_CHARS:
        raise InvalidArgument(f"a {what} name may have at most {MAX_NAME_CHARS} characters")
    parts = global_name(name).strip("/").split("/")
    if len(parts) < 2 or any(not part for part in parts):
        raise InvalidArgument(
            f"{what} {name[:200]!r} must be /SERVICE/PATH with the path's dots as slashes,"
            " like /scout1/location or /scout1/sensors/battery"
        )
    if any("." in part for part in parts):
        raise InvalidArgument(
            f"{what} {name[:200]!r}: write a path's dots as slashes (/scout1/sensors/battery)"
        )
    service, path = parts[0], ".".join(parts[1:])
    if len(parts) == 2 and parts[1] in CONVENTIONS:
        return Target(service, CONVENTIONS[parts[1]][0], parts[1])
    return Target(service, path)


def for_service(target: Target, service_type: str) -> Target:
    """``target`` once its service's type is known: a convention holds for a robot only; for
    another service the last name is a property's own (a sensor's ``pose`` is its ``pose``)."""
    if not target.convention or service_type == MOBILE_ROBOT:
        return target
    return Target(target.service, target.convention)
