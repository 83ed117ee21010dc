"""A picture of who owns what in a cluster: an SVG drawn from the keys of a live cluster.

``python -m gateway.cluster --once --picture docs/scale-out-owners.svg`` starts a cluster, reads its
``gateways``, ``owners`` and ``services`` keys and draws them with :func:`draw_owners`: the shared
store on top, one column per gateway with the services it owns (a device it dialled, or one that
dialled in to it), and a note of what every gateway does for a service owned elsewhere. Plain SVG
text, no imaging library: it is small, diffs as text and renders in any browser.
"""

from __future__ import annotations

from xml.sax.saxutils import escape

from gateway.cluster.records import Ownership

__all__ = ["draw_owners"]

_COLUMN = 290
_MARGIN = 20
_ROW = 22
_TOP = 130


def draw_owners(ownership: Ownership) -> str:
    """The SVG text: the store (its URL) above one column per gateway listing the services it owns."""
    store, gateways, registrations = ownership.store, ownership.gateways, ownership.registrations
    ids = sorted(gateways)
    owned = {gateway: ownership.owned_by(gateway) for gateway in ids}
    orphans = ownership.orphans()
    rows = max([len(names) for names in owned.values()] + [1])
    box_height = 58 + rows * _ROW
    width = _MARGIN * 2 + _COLUMN * max(1, len(ids))
    height = _TOP + box_height + 30 + (22 if orphans else 0) + 44
    parts = [
        f'<svg xmlns="http://www.w3.org/2000/svg" width="{width}" height="{height}" '
        f'viewBox="0 0 {width} {height}" font-family="sans-serif" font-size="13">',
        f'<rect width="{width}" height="{height}" fill="#ffffff"/>',
        _box(width / 2 - 150, _MARGIN, 300, 44, ("#fff4d6", "#c79a1e")),
        _text(width / 2, _MARGIN + 19, "shared registry store", bold=True),
        _text(width / 2, _MARGIN + 36, store),
    ]
    for index, gateway in enumerate(ids):
        record = gateways[gateway]
        left = _MARGIN + index * _COLUMN + 10
        middle = left + (_COLUMN - 20) / 2
        parts.append(
            f'<line x1="{width / 2:g}" y1="{_MARGIN + 44}" x2="{middle:g}" y2="{_TOP}" '
            'stroke="#c79a1e" stroke-dasharray="4 3"/>'
        )
        parts.append(_box(left, _TOP, _COLUMN - 20, box_height, ("#e8f0fb", "#3b6db3")))
        parts.append(_text(middle, _TOP + 20, gateway, bold=True))
        line = f"gRPC {record.address}" + (f" · line {record.line}" if record.line else "")
        parts.append(_text(middle, _TOP + 38, line, size=11))
        for row, name in enumerate(owned[gateway]):
            registration = registrations.get(name)
            dialled_in = registration is not None and registration.dialled_in
            url = registration.url if registration is not None else ""
            top = _TOP + 50 + row * _ROW
            colours = ("#eef8ee", "#5a9a5a") if dialled_in else ("#ffffff", "#8aa6cf")
            parts.append(_box(left + 10, top, _COLUMN - 40, _ROW - 4, colours))
            parts.append(_text(left + 18, top + 13, name, size=11, anchor="start", bold=True))
            parts.append(_text(left + _COLUMN - 38, top + 13, url, size=10, anchor="end"))
    bottom = _TOP + box_height + 28
    if orphans:
        parts.append(_text(width / 2, bottom, "owned by no live gateway: " + ", ".join(orphans), size=12))
        bottom += 22
    notes = (
        "white: registered by a Set on any gateway, dialled by its owner; green: dialled in to its owner.",
        "Every gateway serves every service: a call for one owned elsewhere is forwarded to its owner.",
    )
    for offset, note in enumerate(notes):
        parts.append(_text(width / 2, bottom + offset * 18, note, size=12))
    parts.append("</svg>")
    return "\n".join(parts) + "\n"


def _box(x: float, y: float, w: float, h: float, colours: tuple[str, str]) -> str:
    fill, stroke = colours
    return f'<rect x="{x:g}" y="{y:g}" width="{w:g}" height="{h:g}" rx="6" fill="{fill}" stroke="{stroke}"/>'


def _text(
    x: float, y: float, text: str, *, bold: bool = False, size: int = 13, anchor: str = "middle"
) -> str:
    weight = ' font-weight="bold"' if bold else ""
    return (
        f'<text x="{x:g}" y="{y:g}" text-anchor="{anchor}" font-size="{size}"{weight}>{escape(text)}</text>'
    )
