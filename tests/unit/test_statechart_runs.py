"""Running charts in a State Machine Service over a directory of in-process services.

Each test loads a chart by a Set of ``M.definition`` on the service (a
``LocalService``, as the gateway serves it), starts it and watches its
``state``, ``variables`` and ``log`` properties; the services a chart drives
are real in-process backends.
"""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any

import pytest
from support.fake_backend import DictBackend
from support.group_support import MemoryDirectory
from support.waiting import eventually

from services.apps.statemachine import StateMachineService
from services.apps.statemachine.interpreter import MAX_ACTIONS, MAX_QUEUED_EVENTS
from services.kernel.backend import NO_PARAMS
from services.kernel.core import LocalService, Prop, Resource, action, query
from services.kernel.errors import FailedPrecondition, InvalidArgument, NotFound, ResourceExhausted

HEAD = '<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml"'


async def service(
    directory: MemoryDirectory | None = None, **options: Any
) -> tuple[LocalService, MemoryDirectory]:
    directory = directory or MemoryDirectory()
    backend = LocalService(StateMachineService(directory=directory, **options))
    await directory.add("missions", backend)
    return backend, directory


async def run(sm: LocalService, name: str, chart: str) -> None:
    await sm.set(f"{name}.definition", chart)
    await sm.set(f"{name}.start", "")


async def state_becomes(sm: LocalService, name: str, expected: str) -> None:
    await eventually(
        lambda: sm.get(f"{name}.state"), lambda s: s == expected, what=f"{name}.state == {expected}"
    )


async def variables(sm: LocalService, name: str) -> dict[str, Any]:
    loaded: dict[str, Any] = json.loads(await sm.get(f"{name}.variables"))
    return loaded


async def test_compound_states_guards_and_delayed_events() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="outer">
  <datamodel><data id="n" expr="0"/></datamodel>
  <state id="outer" initial="a">
    <transition event="tick" cond="n &gt;= 3" target="end"/>
    <state id="a">
      <onentry><assign location="n" expr="n + 1"/><send event="tick" delay="20ms"/></onentry>
      <transition event="tick" cond="n &lt; 3" target="b"/>
    </state>
    <state id="b"><onentry><raise event="back"/></onentry><transition event="back" target="a"/></state>
  </state>
  <final id="end"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(end)")
    assert await sm.get("m.status") == "done"
    assert (await variables(sm, "m"))["n"] == 3


async def test_parallel_regions_and_their_done_event() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="both">
  <parallel id="both">
    <transition event="done.state.both" target="end"/>
    <state id="r1">
      <state id="r1a"><transition event="one" target="r1done"/></state><final id="r1done"/>
    </state>
    <state id="r2">
      <state id="r2a"><transition event="two" target="r2done"/></state><final id="r2done"/>
    </state>
  </parallel>
  <final id="end"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(both r1 r1a r2 r2a)")
    await sm.set("m.events", "one")
    await state_becomes(sm, "m", "(both r1 r1done r2 r2a)")
    await sm.set("m.events", "two")
    await state_becomes(sm, "m", "(end)")


@pytest.mark.parametrize(("kind", "resumed"), [("shallow", "(work w2 w2b)"), ("deep", "(work w2 w2c)")])
async def test_history_returns_to_where_the_state_was_left(kind: str, resumed: str) -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + f""" initial="work">
  <state id="work" initial="w1">
    <history id="h" type="{kind}"><transition target="w1"/></history>
    <transition event="pause" target="paused"/>
    <state id="w1"><transition event="next" target="w2"/></state>
    <state id="w2" initial="w2b">
      <state id="w2b"><transition event="next" target="w2c"/></state>
      <state id="w2c"/>
    </state>
  </state>
  <state id="paused"><transition event="resume" target="h"/></state>
</scxml>""",
    )
    for event in ("next", "next", "pause"):
        await sm.set("m.events", event)
    await state_becomes(sm, "m", "(paused)")
    await sm.set("m.events", "resume")
    await state_becomes(sm, "m", resumed)


async def test_cancel_stops_a_delayed_event_and_an_event_carries_data() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <datamodel><data id="got" expr="0"/></datamodel>
  <state id="a">
    <onentry><send id="late" event="timeout" delay="50ms"/></onentry>
    <transition event="timeout" target="timedout"/>
    <transition event="set" target="b">
      <cancel sendid="late"/><assign location="got" expr="_event.data"/>
    </transition>
  </state>
  <state id="b"><transition event="timeout" target="timedout"/><transition event="check" target="ok"/></state>
  <final id="timedout"/>
  <final id="ok"/>
</scxml>""",
    )
    await sm.set("m.events", "set", {"data": "(1 2)"})
    await state_becomes(sm, "m", "(b)")
    assert (await variables(sm, "m"))["got"] == [1, 2]
    await eventually(lambda: sm.get("m.log"), lambda log: "-> b on set" in log)
    # The cancelled timer never fires: the next event after it is the one that decides.
    await asyncio.sleep(0.1)
    await sm.set("m.events", "check")
    await state_becomes(sm, "m", "(ok)")


async def test_a_send_to_internal_goes_before_events_already_waiting_outside() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <state id="a">
    <onentry><send event="outside"/><send event="inside" target="#_internal"/></onentry>
    <transition event="inside" target="b"/>
    <transition event="outside" target="wrong"/>
  </state>
  <state id="b"><transition event="outside" target="done"/></state>
  <final id="done"/>
  <final id="wrong"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(done)")


async def test_send_ids_namelists_css2_delays_and_the_event_fields_a_chart_reads() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a" name="courier">
  <datamodel>
    <data id="sent"/><data id="n" expr="7"/><data id="before" expr="_event"/><data id="fields"/>
    <data id="who"/>
  </datamodel>
  <state id="a">
    <onentry>
      <send event="later" delayexpr="'30ms'" idlocation="sent" namelist="n"
            type="http://www.w3.org/TR/scxml/#SCXMLEventProcessor"/>
      <assign location="who" expr="(_name, _sessionid, _ioprocessors['scxml'].location)"/>
    </onentry>
    <transition event="later" target="b">
      <assign location="fields"
              expr="(_event.data.get('n'), _event.origin, _event.origintype, _event.sendid, _event.type)"/>
    </transition>
  </state>
  <final id="b"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(b)")
    found = await variables(sm, "m")
    assert found["before"] is None  # no event yet when the data is set
    assert found["sent"] == "m.send1"
    assert found["who"] == ["courier", "m", "#_scxml_m"]
    processor = "http://www.w3.org/TR/scxml/#SCXMLEventProcessor"
    assert found["fields"] == [7, "#_scxml_m", processor, None, "external"]


async def test_what_the_standard_fails_at_run_time_raises_error_execution_there() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <datamodel><data id="errors" expr="0"/><data id="sendids" expr="()"/></datamodel>
  <state id="a">
    <!-- a failed action skips the rest of its block: one block each -->
    <onentry><assign location="errors" expr="1 = 1"/></onentry>
    <onentry><assign location="_sessionid" expr="'mine'"/></onentry>
    <onentry><send event="x" type="27" id="typed"/></onentry>
    <onentry><send event="x" namelist="nowhere"/></onentry>
    <onentry><send event="x" target="elsewhere"/></onentry>
    <onentry><send event="x" target="#_scxml_nobody" id="far"/><raise event="never"/></onentry>
    <onentry><raise event="checked"/></onentry>
    <transition event="error.execution error.communication">
      <assign location="errors" expr="errors + 1"/>
      <assign location="sendids" expr="sendids + (_event.sendid,)"/>
    </transition>
    <transition event="checked" target="b"/>
  </state>
  <state id="b"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(b)")
    found = await variables(sm, "m")
    assert found["errors"] == 6
    assert found["sendids"] == [None, None, "typed", None, None, "far"]
    log = await sm.get("m.log")
    assert "warning: line 5: <assign>: expr='1 = 1'" in log
    assert "error.communication" in log


async def test_donedata_and_content_give_the_data_of_done_and_sent_events() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="job">
  <datamodel><data id="n" expr="3"/><data id="report"/><data id="order"/></datamodel>
  <state id="job" initial="work">
    <state id="work"><transition target="finished"/></state>
    <final id="finished">
      <donedata><param name="count" location="n"/><param name="twice" expr="n * 2"/></donedata>
    </final>
    <transition event="done.state.job" target="ordering">
      <assign location="report" expr="(_event.data.count, _event.data.twice)"/>
    </transition>
  </state>
  <state id="ordering">
    <onentry><send event="order"><content>{ "item": "bolt", "sizes": [3, 4] }</content></send></onentry>
    <transition event="order" target="end"><assign location="order" expr="_event.data['item']"/></transition>
  </state>
  <final id="end"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(end)")
    found = await variables(sm, "m")
    assert found["report"] == [3, 6]
    assert found["order"] == "bolt"


class Thermometer(Resource):
    """A sensor whose reading the test sets."""

    resource_type = "sensor"
    data: Annotated[float, Prop(doc="reading")]

    def __init__(self) -> None:
        self.data = 20.0


class Slow(Resource):
    """A service whose action never answers in time."""

    @action
    async def go(self) -> None:
        await asyncio.sleep(30)

    @query
    def nothing(self) -> str:
        return ""


async def test_listen_conditions_raise_events_and_actions_set_and_get_properties() -> None:
    directory = MemoryDirectory()
    thermo = Thermometer()
    await directory.add("thermo1", LocalService(thermo))
    lamp = DictBackend({"on": "false", "level": "3"})
    await directory.add("lamp", lamp)
    sm, _ = await service(directory)
    await run(
        sm,
        "m",
        HEAD
        + """ initial="watch">
  <datamodel><data id="level" expr="0"/><data id="limit" expr="30"/></datamodel>
  <state id="watch">
    <onentry><ps:get property="lamp/level" location="level"/></onentry>
    <ps:listen property="thermo1/data" event="hot" cond="_value &gt; limit"/>
    <transition event="hot" target="alarm"/>
  </state>
  <state id="alarm">
    <onentry><ps:set property="lamp/on" expr="level &gt; 2"/></onentry>
  </state>
</scxml>""",
    )
    await state_becomes(sm, "m", "(watch)")
    assert (await variables(sm, "m"))["level"] == 3
    thermo.data = 25.0
    thermo.data = 31.0
    await state_becomes(sm, "m", "(alarm)")
    assert lamp.values["on"] == "true"


async def test_an_action_that_runs_out_of_time_is_an_error_event_and_is_logged() -> None:
    directory = MemoryDirectory()
    await directory.add("slow", LocalService(Slow()))
    sm, _ = await service(directory)
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <datamodel><data id="code" expr="''"/></datamodel>
  <state id="a">
    <onentry><ps:set property="slow/go" value="" timeout="50ms"/></onentry>
    <transition event="error.action" target="b"><assign location="code" expr="_event.data.code"/></transition>
  </state>
  <state id="b"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(b)")
    assert (await variables(sm, "m"))["code"] == "DEADLINE_EXCEEDED"
    assert "error.action: slow/go: DEADLINE_EXCEEDED" in await sm.get("m.log")


async def test_an_expression_that_fails_while_running_is_error_execution() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <datamodel><data id="w" expr="[1]"/></datamodel>
  <state id="a">
    <onentry><log label="never" expr="w[5]"/></onentry>
    <transition event="error.execution" target="b"/>
  </state>
  <state id="b"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(b)")
    assert "IndexError" in await sm.get("m.log")


async def test_an_eventless_loop_stops_the_machine_instead_of_hanging_the_gateway() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <state id="a"><transition target="b"/></state>
  <state id="b"><transition target="a"/></state>
</scxml>""",
    )
    status = await eventually(lambda: sm.get("m.status"), lambda s: s != "running")
    assert status.startswith("failed: more than 1000 steps")


async def test_nested_foreach_loops_neither_stall_the_event_loop_nor_run_without_end() -> None:
    sm, _ = await service()
    await sm.set(
        "m.definition",
        HEAD
        + """ initial="a">
  <datamodel><data id="w" expr="[0] * 1000"/><data id="x" expr="0"/><data id="y" expr="0"/>
    <data id="n" expr="0"/></datamodel>
  <state id="a"><onentry>
    <foreach array="w" item="x"><foreach array="w" item="y"><assign location="n" expr="n + 1"/>
    </foreach></foreach>
  </onentry></state>
</scxml>""",
    )
    stalls: list[float] = []

    async def ticker() -> None:
        last = time.perf_counter()
        while True:
            await asyncio.sleep(0.005)
            now = time.perf_counter()
            stalls.append(now - last)
            last = now

    ticking = asyncio.create_task(ticker())
    began = time.perf_counter()
    try:
        await sm.set("m.start", "")
        status = await eventually(lambda: sm.get("m.status"), lambda s: s != "running", within=30)
    finally:
        ticking.cancel()
    ran = time.perf_counter() - began
    assert status.startswith(f"failed: more than {MAX_ACTIONS} actions"), status
    # A run that never gave the loop back would be one stall as long as the run, with no tick in
    # it. The bound is half the run (at least 0.5 s): a busy machine may take the process off its
    # core for a while, which is no stall of the loop's making.
    assert len(stalls) >= 20, f"the loop ticked {len(stalls)} times in {ran:.2f} s"
    assert max(stalls) < max(0.5, ran / 2), f"stood still {max(stalls):.2f} s of {ran:.2f} s"


async def test_a_chart_that_sends_itself_events_without_end_lets_the_gateway_run() -> None:
    sm, _ = await service()
    await sm.set(
        "m.definition",
        HEAD
        + """ initial="a">
  <datamodel><data id="n" expr="0"/></datamodel>
  <state id="a">
    <onentry><assign location="n" expr="n + 1"/><send event="again"/></onentry>
    <transition event="again" target="a"/>
  </state>
</scxml>""",
    )
    await sm.set("m.start", "")
    started = time.perf_counter()
    await asyncio.wait_for(asyncio.sleep(0.2), 2)  # the event loop still runs other tasks
    assert time.perf_counter() - started < 1.0
    assert (await variables(sm, "m"))["n"] > 1
    await asyncio.wait_for(sm.set("m.stop", ""), 5)
    assert await sm.get("m.status") == "stopped"


async def test_the_event_queue_is_bounded() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a"><state id="a"><onentry><ps:set property="nobody/x" value="1"/></onentry>
  </state></scxml>""",
    )
    # Sets of events answer without waiting, so the machine's task cannot take any of them in between.
    for i in range(MAX_QUEUED_EVENTS):
        await sm.set("m.events", f"e{i}")
    with pytest.raises(ResourceExhausted):
        await sm.set("m.events", "one-too-many")


async def test_machines_are_made_replaced_and_removed_by_sets_of_their_definition() -> None:
    sm, _ = await service(max_machines=2)
    chart = HEAD + ' initial="a"><state id="a"/></scxml>'
    await sm.set("one.definition", chart)
    await sm.set("two.definition", chart)
    assert await sm.get("machines") == "(one two)"
    with pytest.raises(ResourceExhausted):
        await sm.set("three.definition", chart)
    with pytest.raises(NotFound):
        await sm.set("one.nothing", "x")
    await sm.set("one.start", "")
    with pytest.raises(FailedPrecondition):
        await sm.set("one.definition", chart)
    await sm.set("one.stop", "")
    await sm.set("one.remove", "")
    assert await sm.get("machines") == "(two)"
    with pytest.raises(InvalidArgument):
        await sm.set("bad.definition", "<scxml><nonsense/></scxml>")
    assert await sm.get("machines") == "(two)"


class FolderBackend(DictBackend):
    """``file`` read and written with a ``name`` parameter, ``files`` listing them: the storage contract."""

    def __init__(self) -> None:
        super().__init__({"files": "()"}, type="storage")
        self.content: dict[str, str] = {}

    async def get(self, path: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        if path == "files":
            return "(" + " ".join(sorted(self.content)) + ")"
        if path == "file":
            return self.content[params["name"]]
        return await super().get(path, params)

    async def set(self, path: str, value: str, params: Mapping[str, str] = NO_PARAMS) -> str:
        assert path == "file"
        if value:
            self.content[params["name"]] = value
        else:
            self.content.pop(params["name"], None)
        return ""


async def test_charts_are_stored_and_loaded_again_by_a_new_service() -> None:
    directory = MemoryDirectory()
    storage = FolderBackend()
    await directory.add("store", storage)
    sm, _ = await service(directory, storage="store")
    chart = HEAD + ' initial="a"><state id="a"/></scxml>'
    await sm.set("kept.definition", chart)
    await sm.set("gone.definition", '{"scxml": {"children": [{"state": {"id": "a"}}]}}')
    assert sorted(storage.content) == ["statecharts/gone.json", "statecharts/kept.scxml"]
    await sm.set("gone.remove", "")
    assert sorted(storage.content) == ["statecharts/kept.scxml"]
    await sm.aclose()
    del directory.backends["missions"]

    again, _ = await service(directory, storage="store")
    assert await again.get("machines") == "(kept)"
    assert await again.get("kept.definition") == chart


@pytest.mark.parametrize(
    ("options", "why"),
    [
        ({"charts": ["patrol"]}, "charts is a table"),
        ({"charts": {"patrol": "builtin:nothing"}}, "no chart 'nothing' is shipped"),
        ({"charts": {"a.b": "builtin:patrol"}}, "no dots"),
        ({"charts": {"p": "/nonexistent/p.scxml"}}, "cannot read the chart file"),
        ({"autostart": "patrol"}, "autostart is a list"),
        ({"autostart": ["nothing"]}, "not among the charts"),
        ({"storage": "a/b"}, "bad service name"),
        ({"action_timeout": 0}, "action_timeout"),
        ({"max_machines": 0}, "max_machines"),
    ],
)
def test_bad_options_are_clear_errors(options: dict[str, Any], why: str) -> None:
    with pytest.raises(InvalidArgument) as refused:
        StateMachineService(directory=MemoryDirectory(), **options)
    assert why in refused.value.message


async def test_a_variable_cannot_grow_beyond_a_value_even_by_sharing_lists() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="grow">
  <datamodel><data id="w" expr="['x' * 100]"/><data id="rounds" expr="0"/></datamodel>
  <state id="grow">
    <transition cond="rounds &lt; 20" target="grow">
      <assign location="rounds" expr="rounds + 1"/><assign location="w" expr="[w, w]"/>
    </transition>
    <transition event="error.execution" target="stopped"/>
  </state>
  <state id="stopped"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(stopped)")
    assert "longer than 65536 written out" in await sm.get("m.log")
    assert len(await sm.get("m.variables")) < 200_000


async def test_stop_exits_the_active_states_so_their_onexit_stops_the_robots() -> None:
    directory = MemoryDirectory()
    robot = DictBackend({"behaviors.moveto": "", "behaviors.stop": ""})
    await directory.add("scout1", robot)
    sm, _ = await service(directory)
    await run(
        sm,
        "m",
        HEAD
        + """ initial="drive">
  <state id="drive">
    <onentry><ps:set property="scout1/behaviors.moveto" value="&lt;marker/&gt;"/></onentry>
    <onexit><ps:set property="scout1/behaviors.stop" value="now"/></onexit>
  </state>
</scxml>""",
    )
    await state_becomes(sm, "m", "(drive)")
    assert robot.values["behaviors.stop"] == ""
    await sm.set("m.stop", "")
    assert robot.values["behaviors.stop"] == "now"
    assert await sm.get("m.state") == "()"
    assert await sm.get("m.status") == "stopped"


async def test_a_machine_offers_exactly_the_documented_properties() -> None:
    sm, _ = await service(charts={"patrol": "builtin:patrol"})
    model = await sm.describe()
    access = {p.name: p.access.value for p in model.properties}
    assert access == {
        "machines": "read",
        "patrol": "read",
        "patrol.definition": "read-write",
        "patrol.start": "action",
        "patrol.stop": "action",
        "patrol.remove": "action",
        "patrol.events": "action",
        "patrol.state": "read",
        "patrol.status": "read",
        "patrol.variables": "read",
        "patrol.log": "read",
        "patrol.diagram": "read",
    }


async def test_internal_and_external_transitions_and_conflicts_between_regions() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="p">
  <datamodel><data id="entered" expr="0"/><data id="winner" expr="''"/></datamodel>
  <state id="p" initial="c">
    <onentry><assign location="entered" expr="entered + 1"/></onentry>
    <transition event="inside" type="internal" target="c"/>
    <transition event="outside" target="c"/>
    <transition event="split" target="both"/>
    <state id="c"/>
  </state>
  <parallel id="both">
    <state id="r1">
      <transition event="leave" target="one"><assign location="winner" expr="'r1'"/></transition>
    </state>
    <state id="r2">
      <transition event="leave" target="two"><assign location="winner" expr="'r2'"/></transition>
    </state>
  </parallel>
  <state id="one"/>
  <state id="two"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(p c)")
    await sm.set("m.events", "inside")  # an internal transition does not leave p
    await sm.set("m.events", "outside")  # an external one leaves p and enters it again
    await eventually(lambda: variables(sm, "m"), lambda v: v["entered"] == 2)
    await sm.set("m.events", "split")
    await state_becomes(sm, "m", "(both r1 r2)")
    # Both regions would leave the parallel state: the first in document order wins, the other is not taken.
    await sm.set("m.events", "leave")
    await state_becomes(sm, "m", "(one)")
    assert (await variables(sm, "m"))["winner"] == "r1"


#: The first YAML example of docs/statemachine.md (read at import: no blocking file I/O in a test's loop).
DOCS_YAML_EXAMPLE = (
    (Path(__file__).resolve().parents[2] / "docs" / "statemachine.md")
    .read_text(encoding="utf-8")
    .split("```yaml\n", 1)[1]
    .split("```", 1)[0]
)


async def test_the_yaml_example_of_the_docs_runs_without_an_error() -> None:
    example = DOCS_YAML_EXAMPLE
    sm, _ = await service()
    await run(sm, "m", example)
    await state_becomes(sm, "m", "(idle)")
    await sm.set("m.events", "go")
    await state_becomes(sm, "m", "(busy)")
    assert "error" not in await sm.get("m.log")


async def test_the_log_names_no_event_for_an_eventless_transition() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="s0">
  <state id="s0"><transition event="go" target="a"/></state>
  <state id="a"><transition target="b"/></state>
  <state id="b"><onentry><raise event="next"/></onentry><transition event="next" target="c"/></state>
  <state id="c"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(s0)")
    await sm.set("m.events", "go")
    await state_becomes(sm, "m", "(c)")
    lines = [line.split(" ", 1)[1] for line in (await sm.get("m.log")).splitlines()]
    assert lines[-3:] == ["s0 -> a on go", "a -> b", "b -> c on next"], lines


async def test_the_log_shows_a_transition_that_leaves_and_reenters_its_own_state() -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="sample">
  <datamodel><data id="n" expr="0"/></datamodel>
  <state id="sample">
    <onentry><assign location="n" expr="n + 1"/></onentry>
    <transition event="tick" cond="n &lt; 3" target="sample"/>
    <transition event="tick" target="end"/>
  </state>
  <final id="end"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(sample)")
    for _ in range(3):
        await sm.set("m.events", "tick")
    await state_becomes(sm, "m", "(end)")
    assert (await variables(sm, "m"))["n"] == 3
    lines = [line.split(" ", 1)[1] for line in (await sm.get("m.log")).splitlines()]
    assert [line for line in lines if "->" in line][-3:] == [
        "sample -> sample on tick",
        "sample -> sample on tick",
        "sample -> end on tick",
    ], lines


@pytest.mark.parametrize(
    ("event", "rule"),
    [
        ("error.action", "raised by the machine itself"),
        ("error", "raised by the machine itself"),
        ("done.state.a", "raised by the machine itself"),
        ("done", "raised by the machine itself"),
        ("*", "'*' is a pattern"),
        ("go.*", "'*' is a pattern"),
        ("", "an event is one name"),
        ("two words", "an event is one name"),
        ("a..b", "an event is one name"),
        (".go", "an event is one name"),
        ("x" * 129, "at most 128"),
    ],
)
async def test_a_client_cannot_send_an_event_the_machine_raises_itself(event: str, rule: str) -> None:
    sm, _ = await service()
    await run(
        sm,
        "m",
        HEAD
        + """ initial="a">
  <state id="a"><transition event="error done *" target="b"/></state>
  <state id="b"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(a)")
    with pytest.raises(InvalidArgument) as refused:
        await sm.set("m.events", event)
    assert rule in refused.value.message
    # Names that only begin like a reserved one are the chart's own.
    await sm.set("m.events", "doneness")
    await state_becomes(sm, "m", "(b)")


async def test_a_stored_chart_whose_file_name_is_no_machine_name_is_skipped_with_a_warning(
    caplog: pytest.LogCaptureFixture,
) -> None:
    directory = MemoryDirectory()
    storage = FolderBackend()
    chart = HEAD + ' initial="a"><state id="a"/></scxml>'
    storage.content = {"statecharts/my.chart.scxml": chart, "statecharts/fine.scxml": chart}
    await directory.add("store", storage)
    with caplog.at_level("WARNING", logger="services.apps.statemachine.service"):
        sm, _ = await service(directory, storage="store")
        await sm.start()
    assert await sm.get("machines") == "(fine)"
    (warning,) = [r.getMessage() for r in caplog.records if "my.chart" in r.getMessage()]
    assert "'my.chart' is not a machine name" in warning
    assert "1 to 64 letters, digits, '_' or '-'" in warning


async def test_a_guard_reads_a_followed_property_and_one_it_cannot_follow_is_error_action() -> None:
    directory = MemoryDirectory()
    thermo = Thermometer()
    await directory.add("thermo1", LocalService(thermo))
    sm, _ = await service(directory)
    await run(
        sm,
        "m",
        HEAD
        + """ initial="idle">
  <datamodel><data id="first" expr="value('thermo1/data')"/><data id="code" expr="''"/></datamodel>
  <state id="idle">
    <transition event="check" cond="value('thermo1/data') &gt; 30" target="hot"/>
    <transition event="check" target="idle"/>
    <transition event="ghost" cond="value('ghost/data') &gt; 0" target="hot"/>
    <transition event="error.action" target="failed">
      <assign location="code" expr="_event.data.code"/>
    </transition>
  </state>
  <state id="hot"><transition event="ghost" target="idle"/></state>
  <state id="failed"/>
</scxml>""",
    )
    await state_becomes(sm, "m", "(idle)")
    assert (await variables(sm, "m"))["first"] == 20.0
    await sm.set("m.events", "check")  # 20: not above 30
    await eventually(lambda: sm.get("m.log"), lambda log: "idle -> idle on check" in log)
    thermo.data = 31.0  # read by the next guard without a Get
    await sm.set("m.events", "check")
    await state_becomes(sm, "m", "(hot)")
    await sm.set("m.events", "ghost")
    await state_becomes(sm, "m", "(idle)")
    await sm.set("m.events", "ghost")
    await state_becomes(sm, "m", "(failed)")
    assert (await variables(sm, "m"))["code"] == "NOT_FOUND"
    log = await sm.get("m.log")
    assert "follow ghost/data: NOT_FOUND" in log
    assert "error.action: ghost/data: NOT_FOUND" in log
    # The machine follows thermo1's data while it runs (the sensor's attribute is watched), not after.
    assert len(thermo._ps_watch.get("data", [])) == 1
    await sm.set("m.stop", "")
    assert thermo._ps_watch.get("data", []) == []
