"""The console's JavaScript: every file parses, and node's test runner passes tests/console_js/.

The console is static files with no build step, so node (when installed) is the one tool that
checks them here: ``node --check`` on each module, then ``node --test`` on the tests of the pure
modules (the value grammar, backoff, the event multiplexer, teleop velocities). Without node
these tests skip and say so; the browser tests (tests/browser/) run the console in Chromium.
"""

from __future__ import annotations

import re
import shutil
import subprocess
from pathlib import Path

import pytest

# node starts once for each module and once for its test runner: seconds, not milliseconds.
pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
CONSOLE = ROOT / "gateway" / "console"
NODE = shutil.which("node")
needs_node = pytest.mark.skipif(
    NODE is None, reason="node is not installed: the console's JavaScript is not checked"
)


def _node(*args: str) -> subprocess.CompletedProcess[str]:
    assert NODE is not None
    return subprocess.run([NODE, *args], cwd=ROOT, capture_output=True, text=True, timeout=60, check=False)


def console_modules() -> list[Path]:
    return sorted((CONSOLE / "js").glob("*.js"))


def test_the_console_has_its_modules() -> None:
    names = {p.name for p in console_modules()}
    assert {"api.js", "events.js", "widgets.js", "map.js", "teleop.js", "inspector.js", "main.js"} <= names
    assert (CONSOLE / "index.html").is_file()
    assert (CONSOLE / "console.css").is_file()


@needs_node
@pytest.mark.parametrize("module", console_modules(), ids=lambda p: p.name)
def test_module_parses(module: Path) -> None:
    result = _node("--check", str(module))
    assert result.returncode == 0, result.stderr


@needs_node
def test_node_tests_of_the_pure_modules_pass() -> None:
    result = _node("--test", "tests/console_js/")
    assert result.returncode == 0, result.stdout[-4000:] + result.stderr[-2000:]
    assert "# fail 0" in result.stdout
    assert "# pass 0" not in result.stdout, "node found no tests in tests/console_js/"


def test_no_inline_script_handlers_or_eval() -> None:
    """The page runs under a strict content policy: no inline handlers or scripts, no eval."""
    html = (CONSOLE / "index.html").read_text(encoding="utf-8")
    assert re.search(r"\son[a-z]+\s*=", html) is None, "inline event handler in index.html"
    for script in re.findall(r"<script\b[^>]*>", html):
        assert "src=" in script, f"inline script in index.html: {script}"
    for module in console_modules():
        text = module.read_text(encoding="utf-8")
        for banned in ("eval(", "new Function(", ".innerHTML", "document.write("):
            assert banned not in text, f"{module.name} uses {banned}"


EXAMPLE = CONSOLE / "examples" / "roslib"


@needs_node
def test_the_roslib_example_page_script_parses() -> None:
    result = _node("--check", str(EXAMPLE / "teleop.js"))
    assert result.returncode == 0, result.stderr


def test_the_roslib_example_page_has_no_inline_scripts_and_loads_roslib_from_its_package() -> None:
    html = (EXAMPLE / "index.html").read_text(encoding="utf-8")
    assert re.search(r"\son[a-z]+\s*=", html) is None, "inline event handler in the example page"
    scripts = re.findall(r"<script\b[^>]*>", html)
    assert all("src=" in script for script in scripts), scripts
    # roslibjs comes from the npm package installed beside the page, never from a copy or a CDN.
    assert '<script src="node_modules/roslib/build/roslib.min.js"></script>' in html
    assert not list(EXAMPLE.glob("roslib*.js")), "a copy of roslibjs beside the page"
    text = (EXAMPLE / "teleop.js").read_text(encoding="utf-8")
    for banned in ("eval(", "new Function(", ".innerHTML", "document.write("):
        assert banned not in text, f"teleop.js uses {banned}"
