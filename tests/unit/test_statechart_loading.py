"""Loading charts: SCXML, JSON and YAML give the same model; a bad chart is refused naming its line."""

from __future__ import annotations

import json
import xml.etree.ElementTree as ET

import pytest
import yaml

from services.apps.statemachine import ChartError, compile_chart, render_svg, shipped_chart

SCXML = """<scxml xmlns="http://www.w3.org/2005/07/scxml" xmlns:ps="urn:propertyservice:scxml" initial="idle">
  <datamodel><data id="n" expr="0"/></datamodel>
  <state id="idle">
    <transition event="go" cond="n &lt; 3" target="busy"/>
  </state>
  <parallel id="busy">
    <state id="left"><ps:listen property="thermo1/data" event="hot" cond="_value &gt; 30"/></state>
    <state id="right">
      <onentry><ps:set property="scout1/behaviors.stop" value=""/></onentry>
    </state>
  </parallel>
</scxml>
"""

MODEL = {
    "scxml": {
        "initial": "idle",
        "children": [
            {"datamodel": {"children": [{"data": {"id": "n", "expr": "0"}}]}},
            {
                "state": {
                    "id": "idle",
                    "children": [{"transition": {"event": "go", "cond": "n < 3", "target": "busy"}}],
                }
            },
            {
                "parallel": {
                    "id": "busy",
                    "children": [
                        {
                            "state": {
                                "id": "left",
                                "children": [
                                    {
                                        "ps:listen": {
                                            "property": "thermo1/data",
                                            "event": "hot",
                                            "cond": "_value > 30",
                                        }
                                    }
                                ],
                            }
                        },
                        {
                            "state": {
                                "id": "right",
                                "children": [
                                    {
                                        "onentry": {
                                            "children": [
                                                {"ps:set": {"property": "scout1/behaviors.stop", "value": ""}}
                                            ]
                                        }
                                    }
                                ],
                            }
                        },
                    ],
                }
            },
        ],
    }
}


OPEN = "<scxml xmlns='http://www.w3.org/2005/07/scxml'>"


def shape(text: str) -> list[tuple[str, str, str | None, list[str]]]:
    chart = compile_chart("m", text)
    return [
        (s.id, s.kind, s.parent.id if s.parent else None, [t.label() for t in s.transitions])
        for s in chart.ordered
    ]


def test_scxml_json_and_yaml_of_the_same_chart_give_the_same_model() -> None:
    expected = [
        ("idle", "atomic", "", ["go [n < 3]"]),
        ("busy", "parallel", "", []),
        ("left", "atomic", "busy", []),
        ("right", "atomic", "busy", []),
    ]
    assert shape(SCXML) == expected
    assert shape(json.dumps(MODEL)) == expected
    assert shape(yaml.safe_dump(MODEL)) == expected
    chart = compile_chart("m", yaml.safe_dump(MODEL))
    assert chart.format == "yaml"
    (listen,) = chart.state("left").listens
    assert (listen.service, listen.path, listen.event) == ("thermo1", "data", "hot")


@pytest.mark.parametrize(
    ("text", "where", "why"),
    [
        (OPEN + "\n<state id='a'>\n<script>import os</script>\n</state></scxml>",
         "line 3", "<script> runs code"),
        (OPEN + "\n<state id='a'>\n"
         "<transition event='go' cond=\"__import__('os')\" target='a'/></state></scxml>",
         "line 3", "__import__"),
        (OPEN + "\n\n<state id='a'><transition event='go' target='nowhere'/>"
         "</state></scxml>", "line 3", "no state with id 'nowhere'"),
        (OPEN + "\n<state id='a'/>\n<state id='a'/></scxml>",
         "line 3", "used twice"),
        (OPEN + "\n<state id='a'>\n<onentry><ps:set xmlns:ps='urn:propertyservice:scxml'"
         " property='scout1' value='1'/></onentry></state></scxml>", "line 3", "expected SERVICE/PATH"),
        (OPEN + "\n<state id='a'><onentry>\n<send event='x' target='#_parent'/>"
         "</onentry></state></scxml>", "line 3", "a chart invokes no other documents"),
        (OPEN + "\n<state id='a'><onentry>\n<send event='x' type='http://www.w3.org/TR/scxml/#BasicHTTPEventProcessor'/>"
         "</onentry></state></scxml>", "line 3", "the Basic HTTP processor is not offered"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond='lambda: 1' target='a'/></state></scxml>",
         "line 3", "Lambda is not allowed"),
        (OPEN + "\n<datamodel><data id='x' src='file:/etc/passwd'/></datamodel><state id='a'/></scxml>",
         "line 2", "a chart never reads files or URLs"),
        (OPEN + "\n<state id='a'>\n<invoke src='other.scxml'/></state></scxml>",
         "line 3", "<invoke>"),
        (OPEN[:-1] + " datamodel='ecmascript'>" + "<state id='a'/></scxml>",
         "line 1", "safe subset of Python"),
        (OPEN + "\n<state id='a'>\n<transiton event='x'/></state></scxml>",
         "line 3", "not allowed in <state>"),
        (OPEN + "\n<state id='a'>\n</stat></scxml>", "line 3", "not well-formed"),
        ('<?xml version="1.0"?>\n<!DOCTYPE x [<!ENTITY a "aaaa">]>\n<scxml/>', "line 2", "document type"),
        ('{"scxml": {"children": [{"state": {"id": "a", "children": [{"script": {}}]}}]}}',
         "scxml.children[0].state.children[0].script", "<script> runs code"),
        ("scxml:\n  children:\n  - state: {id: a\n", "line 4", "not valid YAML"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond='n &lt; 3' target='a'/></state></scxml>",
         "line 3", "'n' is not declared in <datamodel>"),
        (OPEN + "\n<datamodel><data id='n' expr='0'/></datamodel>\n<state id='a'><onentry>\n"
         "<assign location='n' expr='n + _value'/></onentry></state></scxml>",
         "line 4", "'_value' is known only in the cond of a <ps:listen>"),
        (OPEN + "\n<state id='a'><onentry>\n<ps:set xmlns:ps='urn:propertyservice:scxml'"
         " property='scout1/speed' value='1' timeout='0'/></onentry></state></scxml>",
         "line 3", "timeout='0': an action's timeout is more than 0 s (at most 600 s)"),
        (OPEN + "\n<state id='a'><onentry>\n<ps:get xmlns:ps='urn:propertyservice:scxml'"
         " property='scout1/speed' location='x' timeout='601'/></onentry></state></scxml>",
         "line 3", "timeout='601': at most 600 s"),
        (OPEN + "\n<datamodel><data id='p' expr=\"'thermo1/data'\"/></datamodel><state id='a'>\n"
         "<transition event='go' cond='value(p) &gt; 3' target='a'/></state></scxml>",
         "line 3", "value() takes the property written as text, like value('thermo1/data')"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond=\"value('thermo1') &gt; 3\" target='a'/>"
         "</state></scxml>", "line 3", "value('thermo1'): expected SERVICE/PATH"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond=\"value('a/b', 'c/d')\" target='a'/>"
         "</state></scxml>", "line 3", "value() takes the property written as text"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond=\""
         + " + ".join(f"value('s{i}/data')" for i in range(33)) + "\" target='a'/></state></scxml>",
         "line 3", "a chart reads at most 32 properties with value()"),
        (OPEN + "\n<state id='a'>\n<transition event='go' cond=\"In('nowhere')\" target='a'/>"
         "</state></scxml>",
         "line 3", "In('nowhere'): no state with id 'nowhere'"),
        ("scxml:\n  initial: a\n  children:\n  - state:\n      id: a\n      children:\n"
         "      - transition: {event: go, cond: \"open('x')\", target: a}\n",
         "line 7 (scxml.children[0].state.children[0].transition)", "only these functions"),
        ("scxml:\n  initial: a\n  children:\n  - state: {id: a}\n  - state:\n      id: b\n"
         "      children:\n      - transition: {event: go, target: nowhere}\n",
         "line 8 (scxml.children[1].state.children[0].transition)", "no state with id 'nowhere'"),
    ],
)  # fmt: skip
def test_a_bad_chart_is_refused_naming_where_and_why(text: str, where: str, why: str) -> None:
    with pytest.raises(ChartError) as refused:
        compile_chart("m", text)
    message = refused.value.message
    assert message.startswith(where), message
    assert why in message, message


def test_charts_are_bounded_in_size() -> None:
    states = "".join(f"<state id='s{i}'/>" for i in range(300))
    with pytest.raises(ChartError, match="more than 256 states"):
        compile_chart("m", OPEN + states + "</scxml>")
    with pytest.raises(ChartError, match="longer than 65536"):
        compile_chart("m", "<scxml>" + " " * 70000 + "</scxml>")


def test_the_diagram_is_valid_svg_with_the_active_states_marked() -> None:
    chart = compile_chart("patrol", shipped_chart("patrol"))
    svg = ET.fromstring(render_svg(chart, ["patrol", "wait"]))
    assert svg.tag == "{http://www.w3.org/2000/svg}svg"
    boxes = {
        g.get("data-state"): (g.get("class") or "").split() for g in svg.iter("{http://www.w3.org/2000/svg}g")
    }
    assert set(boxes) == {"patrol", "goto", "wait", "returning", "formation", "done", "failed"}
    assert sorted(k for k, classes in boxes.items() if "active" in classes) == ["patrol", "wait"]
    labels = [t.text for t in svg.iter("{http://www.w3.org/2000/svg}text") if t.get("class") == "label"]
    assert "hot" in labels and "arrived" in labels


@pytest.mark.parametrize(
    "text",
    [
        '<?xml version="1.0" encoding="UTF-8"?>\r\n' + SCXML.replace("\n", "\r\n"),
        json.dumps(MODEL, indent=1).replace("\n", "\r\n"),
        yaml.safe_dump(MODEL).replace("\n", "\r\n"),
    ],
    ids=["scxml", "json", "yaml"],
)
def test_a_chart_saved_with_a_byte_order_mark_and_crlf_line_ends_loads(text: str) -> None:
    assert shape("\ufeff" + text) == shape(text)
    assert compile_chart("m", "\ufeff" + text).format == compile_chart("m", text).format


def test_malformed_expressions_load_with_a_warning_and_fail_when_run() -> None:
    chart = compile_chart(
        "m",
        OPEN + "\n<datamodel><data id='x' expr='1 = 1'/></datamodel><state id='a'><onentry>\n"
        "<assign location='_sessionid' expr='1'/></onentry></state></scxml>",
    )
    assert [w.split(": <")[0] for w in chart.warnings] == ["line 2", "line 3"]
    assert "it raises error.execution when evaluated" in chart.warnings[0]
    assert "a system variable, read-only" in chart.warnings[1]
