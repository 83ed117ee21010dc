"""The State Machine Service in a real gateway process, driven and watched as a user would.

The patrol chart shipped with the package drives simulated robots to the end
of its mission while a Listen on ``missions/patrol.state`` shows every
configuration in order; a chart whose action fails handles the error; a
chart with an unsafe expression is refused at load with INVALID_ARGUMENT
naming its line; a chart loaded by a Set is back after a gateway restart,
kept by a storage service.
"""

from __future__ import annotations

import asyncio
import json
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

import aiohttp
import pytest
from support.waiting import eventually

from clients.aio import AsyncClient
from clients.errors import InvalidArgument, NotFound
from services.apps.formations import formation_targets

CONFIG = """
[[services]]
name = "scout1"
type = "sim-robot"
options = { speed = 4.0, tick_hz = 50 }

[[services]]
name = "scout2"
type = "sim-robot"
options = { start = [1.0, 0.0], speed = 4.0, tick_hz = 50 }

[[services]]
name = "thermo1"
type = "sim-sensor"
options = { mean = 20.0, swing = 0.0, noise = 0.0, rate_hz = 20 }

[[services]]
name = "swarm"
type = "group"
options = { members = ["scout1", "scout2"] }

[[services]]
name = "missions"
type = "statemachine"
options = { charts = { patrol = "builtin:patrol" } }
"""

FAILING = """<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml"
  initial="try">
  <datamodel><data id="why" expr="''"/><data id="code" expr="''"/></datamodel>
  <state id="try">
    <onentry>
      <ps:set property="scout1/speed" value="fast"/>
      <ps:set property="scout1/speed" value="1.5"/>
    </onentry>
    <transition event="error.action" target="recovered">
      <assign location="why" expr="_event.data.message"/>
      <assign location="code" expr="_event.data.code"/>
    </transition>
  </state>
  <state id="recovered">
    <onentry><ps:set property="ghost/behaviors.stop" value="" done="never"/></onentry>
    <transition event="error.action" cond="_event.data.code == 'NOT_FOUND'" target="handled"/>
  </state>
  <final id="handled"/>
</scxml>
"""

UNSAFE = """<scxml xmlns="http://www.w3.org/2005/07/scxml" initial="a">
  <state id="a">
    <transition event="go" cond="__import__('os').system('true') == 0" target="b"/>
  </state>
  <final id="b"/>
</scxml>
"""


async def _variables(client: AsyncClient, machine: str) -> dict[str, Any]:
    loaded: dict[str, Any] = json.loads(await client.get("missions", f"{machine}.variables"))
    return loaded


@pytest.mark.timeout(90)
async def test_the_patrol_chart_drives_robots_to_the_end_and_its_state_listen_shows_every_step(
    gateway_process: Any,
) -> None:
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client:
        assert await client.get_names("missions", "machines") == ["patrol"]
        states: list[str] = []
        conflated = 0

        async def watch() -> None:
            nonlocal conflated
            async for event in client.listen("missions", "patrol.state"):
                states.append(event.value)
                conflated += event.conflated
                if event.value == "(done)":
                    return

        watcher = asyncio.create_task(watch())
        await eventually(lambda: asyncio.sleep(0, states), lambda s: s == ["()"], what="the first value")
        await client.set("missions", "patrol.start", "")
        # scout1 patrols until the sensor reads above the threshold: lower it once two waypoints are done.
        await eventually(
            lambda: _variables(client, "patrol"), lambda v: v["visited"] >= 2, within=30, what="two waypoints"
        )
        await client.set("missions", "patrol.events", "threshold", data="19")
        await asyncio.wait_for(watcher, 30)
        assert await client.get("missions", "patrol.status") == "done"

        # Every configuration, in order: () then goto/wait pairs, then home, the formation, the end.
        assert conflated == 0
        assert states[0] == "()"
        patrol = states[1 : states.index("(returning)")]
        assert len(patrol) >= 4 and len(patrol) % 2 == 0, states
        assert patrol == ["(patrol goto)", "(patrol wait)"] * (len(patrol) // 2), states
        assert states[states.index("(returning)") :] == ["(returning)", "(formation)", "(done)"]

        # The robots did what the chart said: scout1 went home, then both took their places in a circle.
        places = formation_targets(["scout1", "scout2"], [0.0, 0.0], "circle", 1.5)
        for name in ("scout1", "scout2"):
            await eventually(
                lambda n=name: client.get_vector(n, "location"),
                lambda v, n=name: abs(v[0] - places[n][0]) < 1e-3 and abs(v[1] - places[n][1]) < 1e-3,
                what=f"{name} in its place of the circle",
            )
        log = (await client.get("missions", "patrol.log")).splitlines()
        transitions = [line.split(" ", 1)[1] for line in log if " -> " in line]
        # The log tells the same story as the Listen, with the events that caused each step.
        assert ["(" + t.split(" -> ")[1].split(" on ")[0] + ")" for t in transitions] == states[1:]
        assert transitions[0] == "() -> patrol goto"
        assert transitions[-3] in ("patrol wait -> returning on hot", "patrol goto -> returning on hot")
        assert transitions[-2:] == ["returning -> formation on home", "formation -> done on formed"]
        svg = ET.fromstring(await client.get("missions", "patrol.diagram"))
        groups = svg.iter("{http://www.w3.org/2000/svg}g")
        active = [g.get("data-state") for g in groups if "active" in (g.get("class") or "").split()]
        assert active == ["done"]


@pytest.mark.timeout(60)
async def test_a_failing_action_raises_an_error_event_that_the_chart_handles(gateway_process: Any) -> None:
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client:
        await client.set("missions", "recovery.definition", FAILING)
        assert await client.get_names("missions", "machines") == ["patrol", "recovery"]
        await client.set("missions", "recovery.start", "")
        await eventually(lambda: client.get("missions", "recovery.status"), lambda s: s == "done")
        assert await client.get("missions", "recovery.state") == "(handled)"
        variables = await _variables(client, "recovery")
        assert variables["code"] == "INVALID_ARGUMENT"
        assert "speed" in variables["why"]
        # The rest of the block was skipped: the second Set never ran.
        assert await client.get_number("scout1", "speed") == 4.0
        log = await client.get("missions", "recovery.log")
        assert "error.action: scout1/speed: INVALID_ARGUMENT" in log
        assert "error.action: ghost/behaviors.stop: NOT_FOUND" in log


@pytest.mark.timeout(60)
async def test_an_unsafe_expression_is_refused_at_load_naming_its_line(gateway_process: Any) -> None:
    gw = gateway_process(CONFIG)
    async with AsyncClient(gw.address) as client:
        with pytest.raises(InvalidArgument) as refused:
            await client.set("missions", "evil.definition", UNSAFE)
        assert "line 3" in str(refused.value)
        assert "__import__" in str(refused.value)
        # Nothing was left behind: no machine, and its properties do not exist.
        assert await client.get_names("missions", "machines") == ["patrol"]
        with pytest.raises(NotFound):
            await client.get("missions", "evil.state")


ERRAND = """<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml" initial="go">
  <state id="go">
    <onentry><ps:set property="scout1/speed" value="0.75" done="set"/></onentry>
    <transition event="set" target="end"/>
  </state>
  <final id="end"/>
</scxml>
"""


#: A chart as an editor on Windows saves it: a byte-order mark, an XML declaration, CRLF line ends.
WINDOWS_SAVED = "\ufeff" + '<?xml version="1.0" encoding="UTF-8"?>\r\n' + ERRAND.replace("\n", "\r\n")
#: The same model in YAML, with a byte-order mark and CRLF line ends.
WINDOWS_YAML = "\ufeffscxml:\r\n  initial: idle\r\n  children:\r\n  - state: {id: idle}\r\n"


@pytest.mark.timeout(90)
async def test_charts_survive_a_gateway_restart_through_the_storage_service(
    gateway_process: Any, tmp_path: Path
) -> None:
    config = f"""
        [[services]]
        name = "store"
        type = "storage"
        options = {{ directory = "{tmp_path / "files"}" }}

        [[services]]
        name = "scout1"
        type = "sim-robot"

        [[services]]
        name = "missions"
        type = "statemachine"
        options = {{ storage = "store" }}
    """
    first = gateway_process(config)
    async with AsyncClient(first.address) as client:
        await client.set("missions", "errand.definition", ERRAND)
        assert await client.get_names("store", "files") == ["statecharts/errand.scxml"]
        assert await client.get("store", "file", name="statecharts/errand.scxml") == ERRAND
    # A chart with a byte-order mark and CRLF line ends loads through the HTTP API.
    async with aiohttp.ClientSession(first.http_url) as http:
        url = "/api/v1/services/missions/properties/windows.definition"
        async with http.put(url, json={"value": WINDOWS_YAML}) as response:
            assert response.status == 200, await response.text()
    assert first.stop() == 0
    # ... and so does one saved that way into the storage service's folder.
    (tmp_path / "files" / "statecharts" / "saved.scxml").write_bytes(WINDOWS_SAVED.encode())

    second = gateway_process(config)
    async with AsyncClient(second.address) as client:
        assert await client.get_names("missions", "machines") == ["errand", "saved", "windows"]
        await client.set("missions", "saved.start", "")
        await eventually(lambda: client.get("missions", "saved.status"), lambda s: s == "done")
        await client.set("missions", "saved.remove", "")
        await client.set("missions", "windows.remove", "")
        assert await client.get("missions", "errand.definition") == ERRAND
        assert await client.get("missions", "errand.status") == "stopped"  # running state is not kept
        await client.set("missions", "errand.start", "")
        await eventually(lambda: client.get("missions", "errand.status"), lambda s: s == "done")
        assert await client.get_number("scout1", "speed") == 0.75
        await client.set("missions", "errand.remove", "")
        assert await client.get_names("store", "files") == []
        assert await client.get_names("missions", "machines") == []


THERMOSTAT = """<scxml xmlns="http://www.w3.org/2005/07/scxml" initial="idle">
  <datamodel><data id="code" expr="''"/></datamodel>
  <state id="idle">
    <transition event="check" cond="value('thermo1/data') &gt; 30" target="hot"/>
    <transition event="check" cond="value('thermo1/data') &gt; 10" target="mild"/>
    <transition event="check" target="cold"/>
  </state>
  <state id="mild">
    <transition event="probe" cond="value('ghost/data') &gt; 0" target="hot"/>
    <transition event="error.action" target="blind">
      <assign location="code" expr="_event.data.code"/>
    </transition>
  </state>
  <state id="hot"/>
  <state id="cold"/>
  <state id="blind"/>
</scxml>
"""


@pytest.mark.timeout(60)
async def test_a_guard_on_a_sensor_reading_chooses_the_transition(gateway_process: Any) -> None:
    gw = gateway_process(CONFIG)  # thermo1 reads 20: not above 30, above 10
    async with AsyncClient(gw.address) as client:
        await client.set("missions", "thermostat.definition", THERMOSTAT)
        await client.set("missions", "thermostat.start", "")
        await eventually(lambda: client.get("missions", "thermostat.state"), lambda s: s == "(idle)")
        await client.set("missions", "thermostat.events", "check")
        await eventually(lambda: client.get("missions", "thermostat.state"), lambda s: s == "(mild)")
        # A property that cannot be followed: its guard raises error.action, which the chart handles.
        await client.set("missions", "thermostat.events", "probe")
        await eventually(lambda: client.get("missions", "thermostat.state"), lambda s: s == "(blind)")
        assert (await _variables(client, "thermostat"))["code"] == "NOT_FOUND"
        log = await client.get("missions", "thermostat.log")
        assert "follow ghost/data: NOT_FOUND" in log
        assert "error.action: ghost/data: NOT_FOUND" in log
