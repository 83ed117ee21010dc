"""Chart documents as one tree of elements, whatever their format: SCXML, JSON or YAML.

SCXML is read with expat directly so that every element keeps the line it
starts on (an error names it); as defusedxml does, a document type
declaration, an entity or an external reference is refused outright. JSON
and YAML write the same elements as mappings of one key each (the element's
name) whose value holds the attributes and a ``children`` list::

    {"scxml": {"initial": "idle", "children": [
        {"state": {"id": "idle", "children": [{"transition": {"event": "go", "target": "busy"}}]}},
        {"final": {"id": "busy"}}]}}

An error in those names the element's place (``scxml.children[0].state``), in YAML
after the line the element starts on (``line 7 (scxml.children[0].state)``); the json
module keeps no lines.
"""

from __future__ import annotations

import json
import xml.parsers.expat
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

from services.kernel.errors import InvalidArgument

__all__ = [
    "MAX_CHART_CHARS",
    "MAX_DEPTH",
    "MAX_ELEMENTS",
    "PS_NAMESPACE",
    "SCXML_NAMESPACE",
    "ChartError",
    "Node",
    "detect_format",
    "read_document",
]

SCXML_NAMESPACE = "http://www.w3.org/2005/07/scxml"
#: The namespace of the elements that bind a chart to Property Services (``ps:set``, ``ps:listen``, ...).
PS_NAMESPACE = "urn:propertyservice:scxml"
#: Longest chart text: one property value.
MAX_CHART_CHARS = 65536
#: Most elements in one chart; a chart of a few hundred states is already hard to read.
MAX_ELEMENTS = 4000
#: Deepest nesting of elements.
MAX_DEPTH = 32


class ChartError(InvalidArgument):
    """A chart that cannot be loaded; the message names the line (or place) and what is wrong."""


@dataclass(slots=True)
class Node:
    """One element: its name (``state``, or ``ps:set`` for the binding's namespace), attributes, children."""

    tag: str
    attrs: dict[str, str]
    where: str
    children: list[Node] = field(default_factory=list)
    text: str = ""

    def fail(self, why: str) -> ChartError:
        return ChartError(f"{self.where}: <{self.tag}>: {why}")


#: The byte-order mark editors on Windows write first (decoded: U+FEFF); a chart may start with it.
BYTE_ORDER_MARK = "\ufeff"


def detect_format(text: str) -> str:
    """``scxml`` (text starting with ``<``), ``json`` (``{``) or ``yaml`` (anything else).

    A leading byte-order mark is not part of the text's start.
    """
    head = text.removeprefix(BYTE_ORDER_MARK).lstrip()[:1]
    if head == "<":
        return "scxml"
    if head == "{":
        return "json"
    return "yaml"


def read_document(text: str) -> tuple[str, Node]:
    """The format and the root element of a chart; ChartError naming where it is malformed."""
    if len(text) > MAX_CHART_CHARS:
        raise ChartError(f"the chart is longer than {MAX_CHART_CHARS} characters")
    fmt = detect_format(text)
    # The mark says the text is UTF-8 (it is decoded already); expat, json and YAML would read it
    # as a character of the document. CRLF line ends need nothing: all three read them.
    text = text.removeprefix(BYTE_ORDER_MARK)
    if fmt == "scxml":
        return fmt, _read_scxml(text)
    if fmt == "json":
        try:
            data = json.loads(text)
        except json.JSONDecodeError as e:
            raise ChartError(f"line {e.lineno}: not valid JSON: {e.msg}") from None
        except RecursionError:
            raise ChartError("the JSON nests too deeply") from None
    else:
        data = _load_yaml(text)
    return fmt, _from_mapping(data, "", 0, [0])


class _LinedDict(dict[Any, Any]):
    """A YAML mapping that knows the line it starts on (1-based)."""

    line = 0


def _load_yaml(text: str) -> Any:
    import yaml

    class Loader(yaml.SafeLoader):
        """The safe loader (only plain mappings, lists and scalars: no tags that make objects);
        each mapping keeps its line, so an error names it."""

    def mapping(loader: yaml.SafeLoader, node: yaml.MappingNode) -> Iterator[_LinedDict]:
        data = _LinedDict()
        data.line = node.start_mark.line + 1
        yield data
        data.update(loader.construct_mapping(node))

    Loader.add_constructor("tag:yaml.org,2002:map", mapping)
    try:
        return yaml.load(text, Loader=Loader)  # a SafeLoader: no tags that make objects
    except yaml.MarkedYAMLError as e:
        mark = e.problem_mark
        line = f"line {mark.line + 1}: " if mark is not None else ""
        raise ChartError(f"{line}not valid YAML: {e.problem}") from None
    except (yaml.YAMLError, RecursionError) as e:
        raise ChartError(f"not valid YAML: {e}") from None


def _from_mapping(data: Any, where: str, depth: int, count: list[int]) -> Node:
    here = where or "the document"
    if isinstance(data, _LinedDict):
        here = f"line {data.line} ({here})"
    if not isinstance(data, dict) or len(data) != 1:
        raise ChartError(f"{here}: an element is a mapping of one key, its name (like {{'state': {{...}}}})")
    ((tag, body),) = data.items()
    path = f"{where}.{tag}" if where else str(tag)
    #: What an error names: the element's place, after its line where the format keeps lines.
    shown = f"line {data.line} ({path})" if isinstance(data, _LinedDict) else path
    if depth > MAX_DEPTH:
        raise ChartError(f"{shown}: elements nest deeper than {MAX_DEPTH} levels")
    count[0] += 1
    if count[0] > MAX_ELEMENTS:
        raise ChartError(f"{shown}: the chart has more than {MAX_ELEMENTS} elements")
    if body is None:
        body = {}
    if not isinstance(body, dict):
        raise ChartError(f"{shown}: expected a mapping of attributes (and children), got {body!r:.40}")
    attrs: dict[str, str] = {}
    children: list[Node] = []
    text = ""
    for key, value in body.items():
        if key == "children":
            if not isinstance(value, list):
                raise ChartError(f"{shown}: children: expected a list of elements")
            children = [
                _from_mapping(c, f"{path}.children[{i}]", depth + 1, count) for i, c in enumerate(value)
            ]
        elif key == "text":
            text = str(value)
        elif isinstance(value, bool):
            attrs[str(key)] = "true" if value else "false"
        elif isinstance(value, str | int | float):
            attrs[str(key)] = str(value)
        else:
            raise ChartError(f"{shown}: {key}: an attribute is text or a number, got {type(value).__name__}")
    return Node(str(tag), attrs, shown, children, text)


def _read_scxml(text: str) -> Node:
    parser = xml.parsers.expat.ParserCreate(namespace_separator="|")
    stack: list[Node] = []
    roots: list[Node] = []
    count = 0

    def where() -> str:
        return f"line {parser.CurrentLineNumber}"

    def refuse(*_: Any) -> int:
        raise ChartError(f"{where()}: document type declarations and entities are not allowed")

    def start(name: str, attributes: dict[str, str]) -> None:
        nonlocal count
        count += 1
        if count > MAX_ELEMENTS:
            raise ChartError(f"{where()}: the chart has more than {MAX_ELEMENTS} elements")
        if len(stack) >= MAX_DEPTH:
            raise ChartError(f"{where()}: elements nest deeper than {MAX_DEPTH} levels")
        node = Node(_local(name, where()), {_attr(k): v for k, v in attributes.items()}, where())
        if stack:
            stack[-1].children.append(node)
        else:
            roots.append(node)
        stack.append(node)

    def end(name: str) -> None:
        stack.pop()

    def characters(data: str) -> None:
        if stack:
            stack[-1].text += data

    parser.StartElementHandler = start
    parser.EndElementHandler = end
    parser.CharacterDataHandler = characters
    parser.StartDoctypeDeclHandler = refuse
    parser.EntityDeclHandler = refuse
    parser.UnparsedEntityDeclHandler = refuse
    parser.ExternalEntityRefHandler = refuse
    try:
        parser.Parse(text, True)
    except xml.parsers.expat.ExpatError as e:
        why = xml.parsers.expat.errors.messages[e.code]
        raise ChartError(f"line {e.lineno}: not well-formed XML: {why}") from None
    if not roots:
        raise ChartError("the document has no element")
    return roots[0]


def _local(name: str, where: str) -> str:
    """``state`` for an element of SCXML's namespace, ``ps:set`` for the binding's; others are refused."""
    ns, sep, local = name.rpartition("|")
    if not sep or ns == SCXML_NAMESPACE:
        return local
    if ns == PS_NAMESPACE:
        return f"ps:{local}"
    raise ChartError(
        f"{where}: <{local}> is in the namespace {ns!r}; a chart uses SCXML's ({SCXML_NAMESPACE}) "
        f"and the Property Service binding's ({PS_NAMESPACE})"
    )


def _attr(name: str) -> str:
    return name.rpartition("|")[2]
