"""``psgateway --help`` tells a new user what the demo serves and where."""

from __future__ import annotations

from gateway.cli import build_parser
from gateway.config import default_config


def test_the_help_names_the_demo_console_and_how_to_move_both_ports() -> None:
    text = build_parser().format_help()
    demo = default_config()
    assert f"http://{demo.http.listen}/" in text, "the demo's console URL"
    assert "HTTP/JSON" in text.split("examples:")[0], "the description names the HTTP front end"
    assert "--listen 127.0.0.1:50052 --http 127.0.0.1:8081" in text, "how to run it beside another gateway"
