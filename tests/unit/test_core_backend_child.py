"""Metadata of a child namespace that is a Backend (a group's member), as ``psctl ls -l`` asks for it."""

from __future__ import annotations

from services.core import LocalService, Resource
from services.simulators import SimRobot


class Holder(Resource):
    """Holds one robot behind its Backend, as a group holds its members."""

    def __init__(self) -> None:
        self.attach("bot", LocalService(SimRobot()))


async def test_meta_of_a_backend_child_namespace() -> None:
    service = LocalService(Holder())
    await service.start()
    try:
        assert await service.get("bot.gui") == "group"
        assert await service.get("bot.parameters") == "()"
        assert await service.get("bot.doc") == ""
        # Below the namespace the child answers for itself.
        assert await service.get("bot.location.gui") == "pose"
        assert await service.get("bot.behaviors.moveto.parameters") == "((frame text world))"
    finally:
        await service.aclose()
