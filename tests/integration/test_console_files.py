"""The console as a browser loads it from a real gateway process: the pages (the console and the
cluster page), the stylesheet, and every ES module that their entry points (main.js, cluster.js)
import, directly or through other modules, each served with a JavaScript content type (a browser
refuses a module served as anything else)."""

from __future__ import annotations

import re
import urllib.error
import urllib.parse
import urllib.request
from collections.abc import Iterator
from html.parser import HTMLParser
from pathlib import Path

import pytest
from support.gateway_process import GatewayProcess, start_gateway

ROOT = Path(__file__).resolve().parents[2]
CONSOLE_JS = ROOT / "gateway" / "console" / "js"

CONFIG = """
[[services]]
name = "scout1"
type = "sim-robot"
"""

# import x from './a.js';  import {a, b} from "./b.js";  import './c.js';  export {x} from './d.js';
_IMPORT = re.compile(r"""^\s*(?:(?:import|export)\s[^'";]*?\bfrom|import)\s*['"]([^'"]+)['"]""", re.MULTILINE)
#: The element ids the browser tests and docs/console.md rely on (the HTTP contract's DOM hooks).
DOM_HOOKS = (
    "services",
    "service-view",
    "map",
    "formation",
    "teleop",
    "joystick",
    "teleop-status",
    "inspector",
    "inspector-service",
    "inspector-path",
    "inspector-value",
    "inspector-get",
    "inspector-set",
    "inspector-listen",
    "inspector-output",
    "inspector-log",
    "connection",
)


class _Page(HTMLParser):
    def __init__(self) -> None:
        super().__init__()
        self.scripts: list[dict[str, str | None]] = []
        self.stylesheets: list[str] = []
        self.ids: set[str] = set()

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if a.get("id"):
            self.ids.add(str(a["id"]))
        if tag == "script":
            self.scripts.append(a)
        if tag == "link" and a.get("rel") == "stylesheet" and a.get("href"):
            self.stylesheets.append(str(a["href"]))


def fetch(url: str) -> tuple[int, str, str]:
    """Status, content type and body text of a GET."""
    try:
        with urllib.request.urlopen(url, timeout=10) as response:
            return response.status, response.headers.get("Content-Type", ""), response.read().decode("utf-8")
    except urllib.error.HTTPError as e:
        return e.code, e.headers.get("Content-Type", ""), e.read().decode("utf-8", "replace")


@pytest.fixture(scope="module")
def gateway(tmp_path_factory: pytest.TempPathFactory) -> Iterator[GatewayProcess]:
    gw = start_gateway(tmp_path_factory.mktemp("console"), CONFIG)
    yield gw
    gw.stop()


@pytest.fixture(scope="module")
def page(gateway: GatewayProcess) -> _Page:
    status, content_type, body = fetch(gateway.http_url)
    assert status == 200
    assert content_type.startswith("text/html")
    parsed = _Page()
    parsed.feed(body)
    return parsed


def test_the_page_has_the_dom_hooks_and_one_module_entry_point(page: _Page) -> None:
    missing = [hook for hook in DOM_HOOKS if hook not in page.ids]
    assert not missing, f"index.html lacks {missing}"
    assert [s.get("type") for s in page.scripts] == ["module"]
    assert page.stylesheets


def test_the_stylesheet_is_served_as_css(gateway: GatewayProcess, page: _Page) -> None:
    for href in page.stylesheets:
        status, content_type, body = fetch(urllib.parse.urljoin(gateway.http_url, href))
        assert status == 200, href
        assert content_type.startswith("text/css"), (href, content_type)
        assert "#map" in body


def test_every_module_import_resolves_to_a_served_javascript_file(
    gateway: GatewayProcess, page: _Page
) -> None:
    status, content_type, body = fetch(urllib.parse.urljoin(gateway.http_url, "/console/cluster.html"))
    assert status == 200 and content_type.startswith("text/html")
    cluster_page = _Page()
    cluster_page.feed(body)
    assert {"members", "devices", "rebalance", "connection"} <= cluster_page.ids
    entries = [str(p.scripts[0]["src"]) for p in (page, cluster_page)]
    seen: set[str] = set()
    todo = [urllib.parse.urljoin(gateway.http_url, entry) for entry in entries]
    while todo:
        url = todo.pop()
        if url in seen:
            continue
        seen.add(url)
        status, content_type, body = fetch(url)
        assert status == 200, f"{url}: HTTP {status} {body[:200]}"
        assert content_type.startswith("text/javascript"), f"{url} is served as {content_type!r}"
        for spec in _IMPORT.findall(body):
            bare = f"{url} imports {spec!r}: a bare module name needs a build step"
            assert spec.startswith(("./", "../", "/")), bare
            todo.append(urllib.parse.urljoin(url, spec))
    served = {Path(urllib.parse.urlparse(u).path).name for u in seen}
    on_disk = {p.name for p in CONSOLE_JS.glob("*.js")}
    assert served == on_disk, f"modules no page loads: {sorted(on_disk - served)}"


def test_a_missing_console_file_is_a_json_404(gateway: GatewayProcess) -> None:
    status, content_type, body = fetch(urllib.parse.urljoin(gateway.http_url, "/console/js/nosuch.js"))
    assert status == 404
    assert content_type.startswith("application/json")
    assert '"NOT_FOUND"' in body
