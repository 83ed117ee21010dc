"""A simulated robot sent by a property of its own, ``goal``, as a navigation stack takes a goal
(``type = "tests.support.courier:Courier"``): a Set of a marker drives it there, and ``goal``
reads back where it is sent (an empty marker before the first)."""

from __future__ import annotations

from typing import Annotated, Any

from services.apps.simulators import SimRobot
from services.kernel.core import Prop
from services.kernel.values import Marker

#: The config line of a courier in a test's world.
COURIER_TYPE = "tests.support.courier:Courier"


class Courier(SimRobot):
    """A :class:`SimRobot` with a ``goal`` property: where it is sent."""

    def __init__(self, **options: Any) -> None:
        self._goal = Marker()
        super().__init__(**options)

    @property
    def goal(self) -> Annotated[Marker, Prop(doc="where the robot is sent: Set a marker with a location")]:
        return self._goal

    @goal.setter
    def goal(self, target: Marker) -> None:
        self.behaviors.moveto(target)  # checks the marker, and sends the robot
        self._goal = target
