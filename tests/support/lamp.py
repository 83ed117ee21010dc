"""A user's own Property Service class, as the README shows one: a lamp."""

from typing import Annotated

from services.kernel.core import Prop, Resource, action


class Lamp(Resource):
    """A light that can be switched and made to blink; its power draw is read-only."""

    resource_type = "light"
    on: bool = False
    watts: Annotated[float, Prop(readonly=True)] = 0.0

    @action
    def blink(self, times: int, *, period: float = 0.5) -> str:
        return f"blinking {times} times every {period} s"
