"""Part (j), in this process: transitions per second of a chart whose every transition Sets a property.

The chart steps between two states; entering each Sets ``counter/value`` (an
in-process service behind the gateway's own :class:`gateway.engine.router.Router`),
counts, and sends itself the next event, so every transition is a macrostep
of its own with one Set, one assignment, one guard and one event. The
baseline is a bare loop of the same number of Sets on the same service
through the same router, measured in the same run: the ratio is what the
state machine adds around each Set.
"""

from __future__ import annotations

import asyncio
import time
from typing import Annotated, Any

from gateway.engine.router import Router
from services.apps.statemachine import StateMachineService
from services.kernel.core import LocalService, Prop, Resource

CHART = """<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml" initial="a">
  <datamodel><data id="n" expr="0"/><data id="total" expr="{total}"/></datamodel>
  <state id="a">
    <onentry>
      <ps:set property="counter/value" expr="n"/><assign location="n" expr="n + 1"/><send event="next"/>
    </onentry>
    <transition event="next" cond="n &lt; total" target="b"/>
    <transition event="next" target="end"/>
  </state>
  <state id="b">
    <onentry>
      <ps:set property="counter/value" expr="n"/><assign location="n" expr="n + 1"/><send event="next"/>
    </onentry>
    <transition event="next" cond="n &lt; total" target="a"/>
    <transition event="next" target="end"/>
  </state>
  <final id="end"/>
</scxml>
"""


class Counter(Resource):
    """The service the chart drives: one integer property."""

    value: Annotated[int, Prop(doc="the last count Set")]

    def __init__(self) -> None:
        self.value = 0


async def run_statemachine(transitions: int, time_limit: float) -> dict[str, Any]:
    """Transitions/s of the chart above and Sets/s of a bare loop, on one in-process service."""
    router = Router()
    counter = Counter()
    backend = LocalService(counter)
    await backend.start()
    router.add("counter", backend)
    service = StateMachineService(directory=router)
    machines = LocalService(service)
    await machines.start()
    router.add("missions", machines)
    try:
        # Baseline: the same Sets on the same service, one after another, through the router.
        started = time.perf_counter()
        for i in range(transitions):
            await router.backend("counter").set("value", str(i))
        bare_s = time.perf_counter() - started

        await machines.set("bench.definition", CHART.format(total=transitions))
        ended = asyncio.Event()
        sub = await machines.listen(
            "bench.status", lambda change: ended.set() if change.value != "running" else None
        )
        started = time.perf_counter()
        await machines.set("bench.start", "")
        async with asyncio.timeout(time_limit):
            await ended.wait()
        chart_s = time.perf_counter() - started
        await sub.close()
        status = await machines.get("bench.status")
        complete = status == "done" and counter.value == transitions - 1
        return {
            "transitions": transitions,
            "complete": complete,
            "status": status,
            "chart_s": round(chart_s, 4),
            "bare_s": round(bare_s, 4),
            "transitions_per_s": round(transitions / chart_s, 1),
            "bare_sets_per_s": round(transitions / bare_s, 1),
            "us_per_transition": round(chart_s / transitions * 1e6, 2),
            "us_per_bare_set": round(bare_s / transitions * 1e6, 2),
        }
    finally:
        await machines.aclose()
        await backend.aclose()
