"""An SVG picture of a chart with its active states marked, for the browser console's statechart widget.

A simple nested layout, no Graphviz: an atomic state is a rounded box, a
compound state a box around its children laid out in rows, a parallel state
the same with dashed regions; a transition is an arrow between the two boxes'
edges, labelled with its events and guard. Active states are filled and carry
``class="state active"``; every state box has ``data-state="ID"``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass
from xml.sax.saxutils import escape, quoteattr

from services.apps.statemachine.chart import Chart, State

__all__ = ["render_svg"]

_CHAR_W = 7.0
_BOX_H = 30.0
_PAD = 14.0
_HEADER = 20.0
_GAP = 40.0
_PER_ROW = 4
#: Longest transition label drawn; longer guards are cut with an ellipsis.
_MAX_LABEL = 40


@dataclass(slots=True)
class _Box:
    x: float = 0.0
    y: float = 0.0
    w: float = 0.0
    h: float = 0.0

    @property
    def center(self) -> tuple[float, float]:
        return self.x + self.w / 2, self.y + self.h / 2


def _shown(states: Iterable[State]) -> list[State]:
    return [s for s in states if s.kind != "history"]


def _measure(state: State, boxes: dict[State, _Box]) -> _Box:
    box = boxes.setdefault(state, _Box())
    children = _shown(state.children)
    label_w = max(60.0, _CHAR_W * len(state.id) + 2 * _PAD)
    if not children:
        box.w, box.h = label_w, _BOX_H
        return box
    rows: list[list[_Box]] = []
    for i, child in enumerate(children):
        if i % _PER_ROW == 0:
            rows.append([])
        rows[-1].append(_measure(child, boxes))
    width = max(sum(b.w for b in row) + _GAP * (len(row) - 1) for row in rows)
    height = sum(max(b.h for b in row) for row in rows) + _GAP * (len(rows) - 1)
    box.w = max(label_w, width + 2 * _PAD)
    box.h = height + 2 * _PAD + (_HEADER if state.kind != "root" else 0)
    return box


def _place(state: State, x: float, y: float, boxes: dict[State, _Box]) -> None:
    box = boxes[state]
    box.x, box.y = x, y
    children = _shown(state.children)
    top = y + _PAD + (_HEADER if state.kind != "root" else 0)
    for start in range(0, len(children), _PER_ROW):
        row = children[start : start + _PER_ROW]
        left = x + _PAD
        for child in row:
            _place(child, left, top, boxes)
            left += boxes[child].w + _GAP
        top += max(boxes[c].h for c in row) + _GAP


def _edge_point(box: _Box, toward: tuple[float, float]) -> tuple[float, float]:
    """Where the line from the box's centre toward a point leaves the box."""
    cx, cy = box.center
    dx, dy = toward[0] - cx, toward[1] - cy
    if dx == 0 and dy == 0:
        return cx, cy
    scale = min(
        (box.w / 2) / abs(dx) if dx else math.inf,
        (box.h / 2) / abs(dy) if dy else math.inf,
    )
    return cx + dx * scale, cy + dy * scale


def _label(text: str) -> str:
    return text if len(text) <= _MAX_LABEL else text[: _MAX_LABEL - 1] + "…"


def render_svg(chart: Chart, active: Iterable[str] = ()) -> str:
    """The chart as an SVG document; the states in ``active`` are highlighted."""
    boxes: dict[State, _Box] = {}
    _measure(chart.root, boxes)
    _place(chart.root, 0.0, 0.0, boxes)
    on = set(active)
    root = boxes[chart.root]
    width, height = root.w + 40, root.h + 2  # room for self-transitions on the right
    out = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width:.0f}" height="{height:.0f}"'
        f' viewBox="-1 -1 {width:.0f} {height:.0f}" font-family="sans-serif" font-size="12">',
        f"<title>{escape(chart.name)}</title>",
        '<defs><marker id="arrow" viewBox="0 0 10 10" refX="10" refY="5" markerWidth="8" markerHeight="8"'
        ' orient="auto-start-reverse"><path d="M 0 0 L 10 5 L 0 10 z" fill="#555"/></marker></defs>',
        "<style>.state rect{fill:#fff;stroke:#333}.state.active>rect{fill:#cfe8ff;stroke:#0a58ca;"
        "stroke-width:2}.state.final>rect{stroke-width:3}.parallel>rect{stroke-dasharray:6 3}"
        ".transition{stroke:#555;fill:none}.label{fill:#333}</style>",
    ]
    for state in chart.ordered:
        if state.kind == "history":
            continue
        box = boxes[state]
        classes = ["state", state.kind] + (["active"] if state.id in on else [])
        leaf = not _shown(state.children)
        text_y = box.y + (box.h / 2 + 4 if leaf else 14)
        text_x = box.x + (box.w / 2 if leaf else 8)
        anchor = "middle" if leaf else "start"
        out.append(
            f'<g class="{" ".join(classes)}" data-state={quoteattr(state.id)}>'
            f'<rect x="{box.x:.1f}" y="{box.y:.1f}" width="{box.w:.1f}" height="{box.h:.1f}" rx="8"/>'
            f'<text x="{text_x:.1f}" y="{text_y:.1f}" text-anchor="{anchor}">{escape(state.id)}</text></g>'
        )
    for t in chart.transitions:
        if t.source.kind in ("root", "history") or t is t.source.initial:
            continue
        for target in t.targets:
            source_box = boxes[t.source]
            target_box = boxes.get(target if target.kind != "history" else target.parent or chart.root)
            if target_box is None:
                continue
            if target is t.source:
                x, y = source_box.x + source_box.w, source_box.y + source_box.h / 2
                path = (
                    f"M {x:.1f} {y - 6:.1f} C {x + 30:.1f} {y - 30:.1f}"
                    f" {x + 30:.1f} {y + 30:.1f} {x:.1f} {y + 6:.1f}"
                )
                lx, ly = x + 24, y - 18
            else:
                x1, y1 = _edge_point(source_box, target_box.center)
                x2, y2 = _edge_point(target_box, source_box.center)
                path = f"M {x1:.1f} {y1:.1f} L {x2:.1f} {y2:.1f}"
                lx, ly = (x1 + x2) / 2, (y1 + y2) / 2 - 4
            out.append(f'<path class="transition" d="{path}" marker-end="url(#arrow)"/>')
            label = t.label()
            if label:
                out.append(f'<text class="label" x="{lx:.1f}" y="{ly:.1f}">{escape(_label(label))}</text>')
    out.append("</svg>")
    return "".join(out)
