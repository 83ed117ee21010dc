"""A small service for the HTTP front end's tests, served by a real gateway process by import path
(``type = "tests.support.board:Board"``): a text note, a vector, a switch, a bounded number and
an action with a parameter."""

from typing import Annotated

import numpy as np

from services.kernel.core import Prop, Resource, Vector, action

BOARD_TYPE = "tests.support.board:Board"


class Board(Resource):
    """A notice board: every kind of value a Set through JSON can carry."""

    resource_type = "board"
    note: str = ""
    point: Vector
    lit: bool = False
    level: Annotated[float, Prop(minimum=0.0, maximum=10.0, unit="m", resolution=0.01)] = 0.0

    def __init__(self) -> None:
        self.point = np.zeros(2)

    @action
    def ring(self, times: int, *, tone: str = "low") -> str:
        return f"rang {times} times, {tone}"
